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

from .axis import axis_from_moments, fit_axis
from .errors import InputError, JointfitError, MissingDependencyError, NotIdentifiableError
from .moments import MarkerMoments, moments_from_markers
from .results import AxisFit, CentreFit, SegmentsAxisFit, SegmentsCentreFit
from .segments import fit_axis_two_segments, fit_centre_two_segments
from .sphere import centre_from_moments, fit_centre

__all__ = [
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

from .chain import ChainJoint, fit_chain, leg_chain_spec, virtual_markers
from .identifiability import Identifiability, check_marker_counts, marker_count_identifiability
from .minimal import fit_axis_minimal, fit_centre_minimal, r21_closed_form, s22_closed_form
from .results import MinimalAxisFit, MinimalCentreFit

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
