"""Mitsuba 3 plugins for fiber bundles: BSDFs ``fiber_bundle`` and ``fiber_table``, integrator ``bundle_path``.

Usage, after choosing a variant at your entry point::

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral")
    import mitsuba_ext
    mitsuba_ext.register()          # now {'type': 'fiber_bundle'} and 'bundle_path' load

Python plugins derive from the active variant's classes, so call :func:`register`
again after switching variants.
"""


def register() -> None:
    """Register ``fiber_bundle``, ``fiber_table`` and ``bundle_path`` for the active Mitsuba variant."""
    import mitsuba as mi

    if mi.variant() is None:
        raise RuntimeError("mitsuba_ext.register(): choose a variant first, e.g. mi.set_variant('llvm_ad_rgb')")
    from mitsuba_ext.bsdf import bsdf_classes
    from mitsuba_ext.integrator import integrator_class

    for name, cls in bsdf_classes().items():
        mi.register_bsdf(name, lambda props, cls=cls: cls(props))
    integrator = integrator_class()
    mi.register_integrator("bundle_path", lambda props: integrator(props))
