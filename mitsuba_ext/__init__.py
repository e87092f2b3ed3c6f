"""Mitsuba 3 plugins for fiber bundles: the ``fiber_bundle`` BSDF and ``bundle_path``.

Usage, after choosing a variant at your entry point::

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral")
    import mitsuba_ext
    mitsuba_ext.register()          # now {'type': 'fiber_bundle'} and 'bundle_path' load

Python plugins derive from the active variant's classes, so call :func:`register`
again after switching variants.
"""


def register() -> None:
    """Register ``fiber_bundle`` and ``bundle_path`` for the active Mitsuba variant."""
    import mitsuba as mi

    if mi.variant() is None:
        raise RuntimeError("mitsuba_ext.register(): choose a variant first, e.g. mi.set_variant('llvm_ad_rgb')")
    from mitsuba_ext.bsdf import bsdf_class
    from mitsuba_ext.integrator import integrator_class

    bsdf, integrator = bsdf_class(), integrator_class()
    mi.register_bsdf("fiber_bundle", lambda props: bsdf(props))
    mi.register_integrator("bundle_path", lambda props: integrator(props))
