"""The bake: paths through a bundle of fibers, tallied into its scattering table.

=============  ====================================================================
``tally``      :class:`BakeSpec` (what to tabulate, how) and :class:`Tally` (the sums)
``scene``      :class:`BundleScene`: the fibers as Mitsuba cylinders, 2D ray casts
``baker``      :class:`Baker`: the tracer (the fast estimator, the thesis baseline)
``camera``     :class:`CameraBaker`: the curve exit's table traced from the camera
``twisted``    :class:`~models.bake.twisted.TwistedBaker`: helical plies in 3D (and
               ``twisted_camera``, traced from the camera)
``tables``     :func:`tally_to_table`; :func:`bake_unreduced`, a small bake in one call
=============  ====================================================================
"""

from .baker import Baker
from .camera import CameraBaker
from .scene import BundleScene
from .tables import bake_unreduced, tally_to_table
from .tally import EXITS, BakeSpec, Tally

__all__ = ["Baker", "CameraBaker", "BakeSpec", "BundleScene", "EXITS", "Tally", "bake_unreduced", "tally_to_table"]
