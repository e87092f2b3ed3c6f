"""Mitsuba 3 plugins for fiber bundles: BSDFs ``fiber_bundle``, ``fiber_table`` and
``fiber_ray``, integrator ``bundle_path``; ``hair_resampled``, Mitsuba's ``hair`` sampled as
its density says.

Usage, after choosing a variant at your entry point::

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral")
    import mitsuba_ext
    mitsuba_ext.register()          # now {'type': 'fiber_bundle'} and 'bundle_path' load

    with mitsuba_ext.variant("llvm_ad_mono"):   # another variant for a block, then back
        ...
    with mitsuba_ext.evaluated_mode():          # what the onnx backend renders in
        image = mi.render(scene)
    mitsuba_ext.check_integrator(scene)         # None, or why its integrator cannot render its bundles

Python plugins derive from the active variant's classes, so call :func:`register`
again after switching variants. The modules:

=================  =================================================================
``bsdf``           the BSDF plugin classes (need a variant at import)
``hair``           Mitsuba's ``hair`` with its residual sampled from its own lobe
``integrator``     the ``bundle_path`` class (needs a variant at import)
``frame``          the bundle frame along a curve, angles, spectra to colours
``crossing``       displaced exits, the far side, checks of a scene's bundles
``backends``       how ``fiber_bundle`` evaluates S: table, ONNX, jitted MLP
``table``          the bundle table's lookup in Dr.Jit
``neural``         the exported MLP in onnxruntime and as Dr.Jit arithmetic
``sampling``       importance sampling of outgoing directions from cells
``params``         typed readers of plugin parameters
=================  =================================================================
"""

import contextlib
import importlib

import drjit as dr
import mitsuba as mi

from mitsuba_ext.crossing import check_integrator  # noqa: F401  (why a loaded scene cannot render its bundles)


def plugin_modules() -> list:
    """The plugin modules, imported for the active variant (reloaded after a switch)."""
    if mi.variant() is None:
        raise RuntimeError("mitsuba_ext.register(): choose a variant first, e.g. mi.set_variant('llvm_ad_rgb')")
    modules = []
    for name in ("mitsuba_ext.bsdf", "mitsuba_ext.hair", "mitsuba_ext.integrator"):
        module = importlib.import_module(name)
        if module.VARIANT != mi.variant():  # its classes derive from another variant's
            module = importlib.reload(module)
        modules.append(module)
    return modules


def register() -> None:
    """Register ``fiber_bundle``, ``fiber_table``, ``fiber_ray``, ``hair_resampled`` and
    ``bundle_path`` for the active Mitsuba variant."""
    bsdf, hair, integrator = plugin_modules()
    for name, cls in (bsdf.PLUGINS | hair.PLUGINS).items():
        mi.register_bsdf(name, lambda props, cls=cls: cls(props))
    for name, cls in integrator.PLUGINS.items():
        mi.register_integrator(name, lambda props, cls=cls: cls(props))


@contextlib.contextmanager
def variant(name: str):
    """Mitsuba's variant ``name``, with these plugins registered for it, inside the block;
    the variant before it (and its plugins) after, where one was chosen, also when the block
    raises::

        with mitsuba_ext.variant("llvm_ad_mono"):
            image = mi.render(mi.load_dict(scene))     # scene dicts load under this variant
    """
    previous = mi.variant()
    mi.set_variant(name)
    register()
    try:
        yield
    finally:
        if previous is not None and previous != name:
            mi.set_variant(previous)
            register()


@contextlib.contextmanager
def evaluated_mode():
    """Dr.Jit's evaluated mode inside the block (symbolic loops and calls off), as the
    ``onnx`` backend needs: onnxruntime computes outside Dr.Jit's traced kernels. The flags
    as they were after it."""
    flags = dr.flag(dr.JitFlag.SymbolicLoops), dr.flag(dr.JitFlag.SymbolicCalls)
    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)
    try:
        yield
    finally:
        dr.set_flag(dr.JitFlag.SymbolicLoops, flags[0])
        dr.set_flag(dr.JitFlag.SymbolicCalls, flags[1])


def needs_evaluated_mode(scene) -> bool:
    """Whether a loaded scene has a BSDF that evaluates through onnxruntime."""
    return any(getattr(getattr(shape.bsdf(), "backend", None), "name", None) == "onnx" for shape in scene.shapes())
