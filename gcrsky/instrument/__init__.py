"""The instrument: antenna arrays, beams, the response to every mode, redundancy.

- ``antennas``: :class:`AntennaArray`, hexagonal layouts, antenna pairs, sites
- ``beams``: pyuvdata beams evaluated on the sky (unpolarised amplitude), beam files, per-antenna beams
- ``beammodes``: per-antenna beam perturbations in a Zernike basis and the bilinear response sets they need
- ``polarization``: the cross power beam of each visibility product (``"xx"``, ``"yy"``, ``"pI"``, ...) on each pair of beams
- ``response``: the response of every baseline and frequency to every mode at the reference angle: a quadrature over HEALPix rings
- ``response_sht``: the same by healpy transforms (an independent cross-check)
- ``response_ducc``: the same by ducc0 transforms over the beam's rings only (the default where ducc0 imports)
- ``redundancy``: groups of identical baselines, verified; unique-row responses
- ``sources``: the model visibilities of unit-flux point sources at known positions (idealised LSTs or real times)
"""

from .antennas import (
    HERA_HEIGHT_M,
    HERA_LATITUDE_DEG,
    HERA_LONGITUDE_DEG,
    AntennaArray,
    antpairs,
    baseline_vectors,
    hex_array,
    make_array,
)
from .beammodes import BeamModes, beam_modes, combine_responses, mode_responses
from .beams import (
    AIRY_X_MAX,
    JaxAiryBeam,
    JaxGaussianBeam,
    antenna_beams,
    beam_amplitude,
    beam_fwhm_rad,
    check_beam_frequencies,
    fwhm_airy_rad,
    gaussian_beam,
    load_beam,
    unique_beams,
)
from .polarization import (
    PRODUCTS,
    BaselineKernels,
    baseline_kernels,
    cross_power_kernel,
    normalise_pols,
)
from .redundancy import (
    DEFAULT_RTOL,
    DEFAULT_TOL_M,
    RedundantGroups,
    check_redundancy,
    groups_for_array,
    redundant_groups,
    redundant_responses,
    unique_response,
    validate_groups,
)
from .response import (
    SkyGrid,
    analytic_response,
    equatorial_to_enu,
    response_matrix,
    sky_grid,
)
from .response_ducc import response_matrix_ducc
from .response_sht import (
    realified_projection,
    response_matrix_sht,
)
from .sources import (
    FLUX_UNITS,
    icrs_to_corotating,
    point_source_response,
    problem_source_response,
    source_enu,
)

__all__ = [
    "AIRY_X_MAX",
    "DEFAULT_RTOL",
    "DEFAULT_TOL_M",
    "FLUX_UNITS",
    "HERA_HEIGHT_M",
    "HERA_LATITUDE_DEG",
    "HERA_LONGITUDE_DEG",
    "PRODUCTS",
    "AntennaArray",
    "BaselineKernels",
    "BeamModes",
    "JaxAiryBeam",
    "JaxGaussianBeam",
    "RedundantGroups",
    "SkyGrid",
    "analytic_response",
    "antenna_beams",
    "antpairs",
    "baseline_kernels",
    "baseline_vectors",
    "beam_amplitude",
    "beam_fwhm_rad",
    "beam_modes",
    "check_beam_frequencies",
    "check_redundancy",
    "combine_responses",
    "cross_power_kernel",
    "equatorial_to_enu",
    "fwhm_airy_rad",
    "gaussian_beam",
    "groups_for_array",
    "hex_array",
    "icrs_to_corotating",
    "load_beam",
    "make_array",
    "mode_responses",
    "normalise_pols",
    "point_source_response",
    "problem_source_response",
    "realified_projection",
    "redundant_groups",
    "redundant_responses",
    "response_matrix",
    "response_matrix_ducc",
    "response_matrix_sht",
    "sky_grid",
    "source_enu",
    "unique_beams",
    "unique_response",
    "validate_groups",
]
