"""One run of the sampler on a problem, to disk: draws, maps, products and summary; resumable.

:func:`execute` runs a :class:`RunSpec` (draws, solver, output directory) on a
:class:`~gcrsky.model.Problem`, simulated or read from a file; applications add metrics
and figures through report hooks (:class:`ReportHook`; the paper's are in
:mod:`gcrsky.paper.report`).  One module per stage:

- ``spec``: :class:`RunSpec` (:class:`Draws`, :class:`Solver`, :class:`Output`), validated
  on construction; :func:`run_settings`, what identifies a run's draws;
- ``sampling``: what a run samples, one draw stage (:class:`Joint`, :class:`Independent`,
  :class:`JointFrequency`, :class:`Gains`, :class:`Amplitude`, :class:`Beams`): its settings block, files, draws and summary block;
- ``output``: the run's files, :func:`check_output` (refuse / overwrite / resume),
  :func:`remove_run_files`, :func:`open_run`;
- ``resume``: :class:`ResumeError`, :func:`settings_differences`, the recorded solver options;
- ``stages``: :class:`StageTimer`, and :class:`Watch` (how a caller follows a run);
- ``draws``: the joint run's set-up and its batches into ``results.h5`` (the documented key scheme);
- ``gains``: a run that samples the gains with the sky: its chain, batches, gain products and summary;
- ``channels``: independent channels (one at a time, over devices, over processes);
- ``maps``: :class:`RunMaps`: truth, mean, std and Wiener maps, per-mode z-scores;
- ``report``: :class:`ReportHook`, :class:`RunView`: what applications add after the draws;
- ``products``: :func:`write_products`: HEALPix FITS, healpy alm, pyradiosky skyh5;
- ``summary``: :class:`RunSummary` (``summary.json``), :class:`RunProducts`, the solver block;
- ``fit``: :func:`goodness_of_fit`, the posterior predictive check every run writes;
- ``lock``: :func:`run_lock`, one run per output directory;
- ``runner``: :func:`execute`, the stages in order.
"""

from .fit import goodness_of_fit
from .lock import LOCK_FILE, RunLockedError, check_unlocked, lock_owner, run_lock
from .maps import RunMaps, mode_z_scores, parameter_frame, run_maps
from .output import (
    PRODUCT_FILES,
    RESULTS_FILE,
    RUN_FILES,
    SUMMARY_FILE,
    PostDrawError,
    RunExistsError,
    check_out_dir,
    check_output,
    existing_run_files,
    open_run,
    remove_run_files,
)
from .products import write_products
from .report import FigureReport, ReportHook, RunView
from .resume import ResumeError, settings_differences
from .runner import execute
from .sampling import (
    Amplitude,
    AmplitudeSampling,
    Beams,
    BeamSampling,
    DrawStage,
    FrequencyModel,
    Gains,
    GainSampling,
    Independent,
    Joint,
    JointFrequency,
)
from .spec import CHANNEL_MODES, EXISTING, METHODS, Draws, Output, RunSpec, Solver, run_settings
from .stages import StageTimer, Watch
from .summary import RunProducts, RunSummary, info_stats, read_summary, solver_summary, versions

__all__ = [
    "CHANNEL_MODES",
    "EXISTING",
    "LOCK_FILE",
    "METHODS",
    "PRODUCT_FILES",
    "RESULTS_FILE",
    "RUN_FILES",
    "SUMMARY_FILE",
    "DrawStage",
    "Draws",
    "FigureReport",
    "FrequencyModel",
    "GainSampling",
    "Gains",
    "Amplitude",
    "AmplitudeSampling",
    "BeamSampling",
    "Beams",
    "Independent",
    "Joint",
    "JointFrequency",
    "Output",
    "ReportHook",
    "ResumeError",
    "PostDrawError",
    "RunExistsError",
    "RunLockedError",
    "RunMaps",
    "RunProducts",
    "RunSpec",
    "RunSummary",
    "RunView",
    "Solver",
    "StageTimer",
    "Watch",
    "check_out_dir",
    "check_output",
    "check_unlocked",
    "execute",
    "existing_run_files",
    "goodness_of_fit",
    "info_stats",
    "lock_owner",
    "mode_z_scores",
    "open_run",
    "parameter_frame",
    "read_summary",
    "remove_run_files",
    "run_lock",
    "run_maps",
    "run_settings",
    "settings_differences",
    "solver_summary",
    "versions",
    "write_products",
]
