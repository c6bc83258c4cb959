"""``gcrsky run``: simulate the paper's standard case (or a scenario, or a variant), sample it, write the run.

The problem is built by :func:`gcrsky.sim.problem_from_config` and run by
:func:`gcrsky.run.execute` with the paper's report (:func:`gcrsky.paper.pipeline.paper_hooks`).
With ``--data FILE`` the command is :mod:`gcrsky.cli.cmd_data` instead.
"""

from __future__ import annotations

import sys
import time

from ..solvers.options import DEFAULT_TOL
from .options import DEFAULT_NSAMPLES, check_channel_options, check_frequency_options
from .runs import EXIT_REFUSED, execute_with_bars, report_run, run_spec
from .terminal import refusal_message

__all__ = ["run_command", "sim_settings"]

def run_command(args, parser) -> int:
    """``gcrsky run`` (a simulation, or a file with ``--data``): check the options, then run."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    check_channel_options(parser, args)
    check_frequency_options(parser, args)
    if args.trust_recorded and not args.resume:
        parser.error("--trust-recorded continues a recorded run from its recorded inputs: give it with --resume")
    if args.data is not None:
        from .cmd_data import data_command

        return data_command(args, parser)
    from .cmd_data import check_beam_options, check_gain_options

    check_gain_options(parser, args)
    check_beam_options(parser, args)
    if args.lmax is None:  # the simulation's default (with --data: the baselines' reach)
        from ..sim.config import Config

        args.lmax = Config().lmax
    _check_sim_options(parser, args)
    with logging_redirect_tqdm():
        return _run(args)


def _check_sim_options(parser, args) -> None:
    """The LST range runs forwards and the configuration (with the scenario's settings) is valid."""
    if args.lst_stop < args.lst_start:
        parser.error(
            f"--lst-stop ({args.lst_stop:g} h) is before --lst-start ({args.lst_start:g} h); to wrap "
            f"through 0 h give a stop beyond 24 h (e.g. --lst-start 22 --lst-stop 26)"
        )
    from ..sim.config import Config

    try:
        Config(lmax=args.lmax, nside=args.nside, n_lst=args.n_lst,
               lst_range_hours=(args.lst_start, args.lst_stop), obs_date=args.date).validate()
        Config(**sim_settings(args)[0]).validate()
    except ValueError as e:
        parser.error(str(e))


def sim_settings(args):
    """(Config fields, nsamples, method, scenario name or None, tol) from ``gcrsky run`` arguments.

    With ``--scenario``, options left at the standard case's value keep the scenario's
    setting; an option that changes a field the scenario also sets, to another value,
    is an error.
    """
    from ..paper.scenarios import scenario
    from ..sim.config import Config

    fields = dict(
        lmax=args.lmax, nside=args.nside, n_lst=args.n_lst, lst_range_hours=(args.lst_start, args.lst_stop),
        dish_diameter=Config().dish_diameter if args.dish_diameter is None else args.dish_diameter,
        noise_scale=args.noise_scale, prior_scale=args.prior_scale,
        flat_prior=args.flat_prior, zero_prior_mean=args.zero_prior_mean, seed=args.data_seed, obs_date=args.date,
    )
    if args.scenario is None:
        return fields, args.nsamples or DEFAULT_NSAMPLES, args.method or "auto", None, args.tol or DEFAULT_TOL
    sc = scenario(args.scenario)
    d = Config()
    user = {k: v for k, v in fields.items() if v != getattr(d, k)}
    mine = dict(sc.overrides)
    clash = sorted(k for k in user if k in mine and user[k] != mine[k])
    if clash:
        raise ValueError(
            f"scenario {sc.name} sets {', '.join(f'{k}={mine[k]!r}' for k in clash)}; the options ask for "
            f"{', '.join(f'{k}={user[k]!r}' for k in clash)} (drop --scenario to customise freely)"
        )
    return {**mine, **user}, args.nsamples or sc.nsamples, args.method or sc.method, sc.name, args.tol or sc.tol


def _say_resume(state, out) -> None:
    """What ``--resume`` will do with the run in ``out`` (``state``: its ResultsState, or None)."""
    if state is None:
        print(f"gcrsky: --resume: no run in {out} to resume; starting a new one")
    elif state.draws_done:
        print(f"gcrsky: --resume: the run in {out} has all its {state.ndraws_complete} draws"
              + (" and is complete; writing any missing files" if state.complete else "; finishing it"))
    else:
        print(f"gcrsky: --resume: continuing the run in {out} at batch {state.batches_complete} of "
              f"{state.n_batches} ({state.ndraws_complete} of {state.nsamples} draws done)")


def _run(args) -> int:
    """Build the simulated problem and run it (refused, or resumed, before anything is built)."""
    from .setup import setup_jax

    compile0 = setup_jax(args)
    from ..paper.pipeline import paper_hooks
    from ..paper.report import FIGURE_FILES
    from ..run import ResumeError, RunExistsError, check_out_dir, check_output, check_unlocked
    from ..sim.config import Config
    from ..sim.standard import problem_from_config

    fields, nsamples, method, scen, tol = sim_settings(args)
    config = Config(**fields).validate()
    spec = run_spec(args, nsamples=nsamples, method=method, tol=tol, scenario=scen)
    worker = bool(args.process_id)  # a jax.distributed process other than 0: computes, writes nothing
    try:  # refuse (or resume) before the problem is built: the check needs only the settings
        if not worker:
            check_out_dir(spec.output.out)  # a writable directory (the message says what is wrong)
            check_unlocked(spec.output.out)  # another run writes there (execute's lock is what excludes)
        state = None if worker else check_output(spec.output.out, spec.settings(config), spec.output.existing,
                                                 tuple(FIGURE_FILES.values()))
    except (RunExistsError, ResumeError) as e:
        print(refusal_message(e, resume=args.resume), file=sys.stderr)
        return EXIT_REFUSED
    if args.resume:
        _say_resume(state, spec.output.out)
    if not worker:
        spec.output.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    prob = problem_from_config(config)
    done = execute_with_bars(args, prob, spec, paper_hooks(prob), build_s=time.perf_counter() - t0,
                             compile_since=compile0)
    return done if isinstance(done, int) else report_run(*done, spec.output.out, strict=args.strict)
