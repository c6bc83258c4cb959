"""The sphere: the realified mode layout, real harmonics, rotations, frames and maps.

- ``modes``: the realified vector layout (the one module that owns (l, m) indexing): mode tables, ``realify`` / ``unrealify``
- ``harmonics``: real spherical-harmonic basis maps in JAX (Legendre recursion)
- ``rotation``: the sidereal rotation and full Wigner-D rotations (traced angles)
- ``frames``: real observing times: Earth rotation angles, the ICRS -> CIRS-of-date frame map, Galactic -> ICRS
- ``maps``: HEALPix maps of coefficients and of posterior draws (healpy)
"""


from .frames import (
    FrameMap,
    ObservingGeometry,
    alm_frame_matrix,
    apply_frame,
    frame_lmax,
    frame_matrix,
    frame_rotation_matrix,
    hours_to_rad,
    icrs_to_apparent_matrix,
    icrs_to_cirs_map,
    local_sidereal_angles,
    observing_geometry,
    rotate_between_frames,
    times_for_lsts,
    transpose_frame,
)
from .harmonics import (
    legendre_table,
    real_basis,
)
from .maps import (
    alm_to_map,
    posterior_maps,
)
from .modes import (
    ModeTable,
    lmax_from_nparams,
    mode_table,
    n_alm,
    n_params,
    realify,
    unrealify,
)
from .rotation import (
    WignerBlocks,
    euler_zyz,
    from_lm_grid,
    rotate,
    rotate_complex_alm,
    rotate_euler,
    rotate_euler_transpose,
    rotate_matrix,
    rotation_matrix_zyz,
    to_lm_grid,
    wigner_band_edges,
    wigner_blocks,
    wigner_lmax,
    wigner_nbytes,
)

__all__ = [
    "FrameMap",
    "ModeTable",
    "ObservingGeometry",
    "WignerBlocks",
    "alm_frame_matrix",
    "alm_to_map",
    "apply_frame",
    "euler_zyz",
    "frame_lmax",
    "frame_matrix",
    "frame_rotation_matrix",
    "from_lm_grid",
    "hours_to_rad",
    "icrs_to_apparent_matrix",
    "icrs_to_cirs_map",
    "legendre_table",
    "lmax_from_nparams",
    "local_sidereal_angles",
    "mode_table",
    "n_alm",
    "n_params",
    "observing_geometry",
    "posterior_maps",
    "real_basis",
    "realify",
    "rotate",
    "rotate_between_frames",
    "rotate_complex_alm",
    "rotate_euler",
    "rotate_euler_transpose",
    "rotate_matrix",
    "rotation_matrix_zyz",
    "times_for_lsts",
    "to_lm_grid",
    "transpose_frame",
    "unrealify",
    "wigner_band_edges",
    "wigner_blocks",
    "wigner_lmax",
    "wigner_nbytes",
]
