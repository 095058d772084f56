"""Joint centre and axis estimation from motion-capture markers.

Pure numpy/scipy; never imports ROS. Markers are ``(N, P, 3)`` float64 arrays
(time, marker, xyz) in any length unit, NaN for a missing marker.

Main entry points
-----------------
fit_centre
    Ball-joint centre from markers in a frame where it is fixed (Gamage &
    Lasenby 2002 eq. 5, bias-compensated, with covariance).
fit_axis
    Hinge axis from markers in a frame where it is fixed (Gamage & Lasenby
    section 3).
"""

import os as _os

# One BLAS thread unless the user chose otherwise, set before numpy loads OpenBLAS (it reads these once).
# jointfit's matrices are small (3x3 per frame; at most a few thousand rows by ~100 columns per solve):
# threads gain nothing there, and on a shared 2-core machine OpenBLAS threads cost a fit 2-9x its
# single-thread time in CPU and wall clock (bench/results/blas_threads.md) and take the node's cores
# from its marker stream. A variable already set (to any value) is kept; a program that imported
# numpy before jointfit keeps its own setting.
#: The environment variables that set the BLAS libraries' thread counts (OpenBLAS, OpenMP, MKL).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _name in BLAS_THREAD_VARIABLES:
    _os.environ.setdefault(_name, "1")

from .axis import axis_from_moments, fit_axis  # noqa: E402
from .errors import InputError, JointfitError, MissingDependencyError, NotIdentifiableError  # noqa: E402
from .moments import MarkerMoments, moments_from_markers  # noqa: E402
from .results import AxisFit, CentreFit, SegmentsAxisFit, SegmentsCentreFit  # noqa: E402
from .segments import fit_axis_two_segments, fit_centre_two_segments  # noqa: E402
from .sphere import centre_from_moments, fit_centre  # noqa: E402

__all__ = [
    "BLAS_THREAD_VARIABLES",
    "AxisFit",
    "CentreFit",
    "InputError",
    "JointfitError",
    "MarkerMoments",
    "MissingDependencyError",
    "NotIdentifiableError",
    "SegmentsAxisFit",
    "SegmentsCentreFit",
    "axis_from_moments",
    "centre_from_moments",
    "fit_axis",
    "fit_axis_two_segments",
    "fit_centre",
    "fit_centre_two_segments",
    "moments_from_markers",
]

from .chain import ChainJoint, fit_chain, leg_chain_spec, virtual_markers  # noqa: E402
from .identifiability import Identifiability, check_marker_counts, marker_count_identifiability  # noqa: E402
from .minimal import fit_axis_minimal, fit_centre_minimal, r21_closed_form, s22_closed_form  # noqa: E402
from .results import MinimalAxisFit, MinimalCentreFit  # noqa: E402

__all__ += [
    "ChainJoint",
    "Identifiability",
    "MinimalAxisFit",
    "MinimalCentreFit",
    "check_marker_counts",
    "fit_axis_minimal",
    "fit_centre_minimal",
    "fit_chain",
    "leg_chain_spec",
    "marker_count_identifiability",
    "r21_closed_form",
    "s22_closed_form",
    "virtual_markers",
]
__version__ = "0.1.0"
