import pytest


@pytest.fixture(scope="session")
def mi_llvm():
    """Mitsuba on the LLVM backend (chosen here, at the entry point, never at import)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi
