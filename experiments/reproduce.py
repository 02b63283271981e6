"""Re-run every computation behind the papers' results (``results/p00*.md``) with one command.

    python experiments/reproduce.py --dry-run           # list the jobs and their commands
    python experiments/reproduce.py                     # everything, 2 jobs at a time (2 cores)
    python experiments/reproduce.py --only p001 p004    # the jobs whose name starts with one of these
    python experiments/reproduce.py -j 1 --out outputs/reproduce
    python experiments/reproduce.py --collect           # then the sweeps' summary.csv -> results/data, tables rendered

A *job* is one seed sweep (``experiments/train.py -m ... seed=0,1,2,3,4``; two for p002, whose
reports pair its UKF and RC-UKF sweeps) with the commands that read its output (learned values, the
in-distribution test of the best-validation checkpoints, the paired analysis on the paper's
profile), run in order in one shell; jobs are independent of each other and run ``-j`` at a time,
the longest first (every command already uses ``threads=1``).  Each command is written verbatim as
it appears in its results file, up to a ``nice`` prefix and a ``mkdir -p`` of its target folder
(``tests/test_reproduce.py`` checks that), so a job's output directory is the one the results file
cites and its ``summary.md`` can be compared with the table there.  The tables of the results files,
``results/REPORT.md`` and ``results/detail/`` are rendered from ``results/data/*.csv`` (one per
family, the schema of a sweep's ``summary.csv``; ``python experiments/report.py --render``, checked
by ``--check``).  This script recomputes the evidence and leaves ``results/`` alone unless given
``--collect``: then, when every job succeeded, it copies each family's ``<sweep>/summary.csv`` into
``results/data/``, joins the practitioners families' kappa 0 and learned adaptive sweeps to them (to
the committed file where the family's own sweep did not run), renders every table again and runs
the check (``git diff results/`` shows what changed).

Every job's wall time and CPU time (user + system of the job's shell and everything it ran) are
appended to ``<out>/times.tsv`` and summed at the end: the "full REPORT regenerates in <= 2 h on
2 cores" figure of issue 14 is that sum's wall time.  A job's stdout/stderr go to
``<out>/<job>.log``; a failing job is reported and the others go on (exit status 1 at the end).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments import results_report  # noqa: E402

__all__ = ["JOBS", "Job", "main", "select_jobs"]

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Job:
    """One sweep and the commands that read it.

    Attributes:
        name: ``<paper>_<family>``; ``--only`` selects by prefix.
        results: the results file (under ``results/``) whose numbers the job recomputes.
        cpu_s: CPU seconds it took when last measured (the order of the queue; see :data:`JOBS`).
        commands: shell commands, run in order from the repository root; the job stops at the first failure.
    """

    name: str
    results: str
    cpu_s: float
    commands: tuple[str, ...]


def _indist(sweep: str, root: str = "outputs/sweeps") -> tuple[str, str]:
    """The in-distribution test of a sweep's best-validation checkpoints (link them, evaluate them)."""
    link = (
        f"mkdir -p {root}/{sweep}_best && "
        f"for s in 0 1 2 3 4; do ln -sf $PWD/$(ls {root}/{sweep}/$s/checkpoints/epoch_*.ckpt) {root}/{sweep}_best/$s.ckpt; done"
    )
    test = (
        f"python experiments/eval.py -m seed=0,1,2,3,4 'ckpt_path={root}/{sweep}_best/${{seed}}.ckpt' "
        f"config_from_checkpoint=false experiment={sweep} data.test_simulator.randomize=true logger=csv "
        f"hydra.sweep.dir={root}/{sweep}_indist"
    )
    return link, test


def _final(experiment: str, sweep: str, extra: str = "", root: str = "outputs/final") -> str:
    extra = f" {extra}" if extra else ""
    return f"python experiments/train.py -m experiment={experiment}{extra} seed=0,1,2,3,4 hydra.sweep.dir={root}/{sweep}"


def _sweep(experiment: str, root: str = "outputs/sweeps", learned_values: bool = True) -> tuple[str, ...]:
    train = f"python experiments/train.py -m experiment={experiment} seed=0,1,2,3,4 logger=csv hydra.sweep.dir={root}/{experiment}"
    return (train, f"python experiments/learned_values.py sweep_dir={root}/{experiment}") if learned_values else (train,)


def _sweep_and_test(experiment: str, root: str = "outputs/sweeps", learned_values: bool = True) -> tuple[str, ...]:
    """A sweep over seeds, its learned values, and the in-distribution test of its checkpoints."""
    return (*_sweep(experiment, root, learned_values), *_indist(experiment, root))


def _summary_copy(source: str, copy: str, option: str) -> tuple[str, str]:
    """A sweep's jobs copied and summarised against another row (``summarize_sweep``'s ``option``)."""
    return (
        f"mkdir -p {copy} && cp -r {source}/{{0,1,2,3,4}} {copy}/",
        f"python -c \"from experiments.runner.sweep import summarize_sweep; summarize_sweep('{copy}', {option})\"",
    )


def _practitioners(family: str, root: str = "outputs/practitioners") -> tuple[str, str]:
    """A family's sweep with its practitioners' rows, and its summary paired with the best of them."""
    return (
        f"python experiments/train.py -m experiment={family}_practitioners seed=0,1,2,3,4 logger=csv hydra.sweep.dir={root}/{family}",
        f"python -m experiments.practitioners {root}/{family}",
    )


def _learned_adaptive(experiment: str, family: str, root: str = "outputs/practitioners") -> tuple[str]:
    """A learned adaptive sweep (issue 25).  Its rows are joined to the family's data file by
    ``--collect`` (:func:`experiments.results_report.collect`), after the family's own sweep: a join
    in the job would check them against the committed file, before or beside the family's rerun."""
    sweep = f"{root}/{family}_learned_adaptive"
    return (f"python experiments/train.py -m experiment={experiment} seed=0,1,2,3,4 logger=csv hydra.sweep.dir={sweep}",)


def _kappa0(family: str, root: str = "outputs/practitioners") -> tuple[str, ...]:
    """p000's adaptive rows around a kappa 0 UKF (issue 25): their sweep and the learned adaptive
    kappa 0 sweep.  ``--collect`` merges the first into the family's data file and then joins the
    second (in this order: the join pairs with the best row, which the merge may change), after the
    family's own sweep (see :func:`_learned_adaptive`)."""
    k0, adaptive = f"{root}/{family}_k0", f"{root}/{family}_learned_adaptive_k0"
    return (
        f"python experiments/train.py -m experiment={family}_practitioners_k0 seed=0,1,2,3,4 logger=csv hydra.sweep.dir={k0}",
        f"python -m experiments.practitioners {k0}",
        f"python experiments/train.py -m experiment={family}_learned_adaptive_k0 seed=0,1,2,3,4 logger=csv hydra.sweep.dir={adaptive}",
    )


def _p003(experiment: str) -> tuple[str, str]:
    return (
        f"python experiments/train.py -m experiment={experiment} seed=0,1,2,3,4 learner.init_perturbation=0.3 logger=csv "
        f"hydra.sweep.dir=outputs/p003_final/{experiment}",
        f"python experiments/p003_paired.py sweep_dir=outputs/p003_final/{experiment}",
    )


def _diagnostic(seed: int, name: str, accel: str, bias: str, drift: str, r: str, psi: str) -> str:
    """p001's diagnostic run: the per-channel filter started from given values (no perturbation)."""
    start = f"accel_psd:[{accel}],clock_bias_psd:{bias},clock_drift_psd:{drift},R:[{','.join([r] * 7)}],psi:[{psi}]"
    return (
        f"python experiments/train.py experiment=p001_multipath logger=csv learner.init_perturbation=0 seed={seed} "
        f"'learner.start_params={{{start}}}' hydra.run.dir=outputs/sweeps/p001_multipath_diag/{name}"
    )


_SEED3 = (
    "1.174280025597408e-10,1.0355852011337935e-10,1.0179549044914812e-10",
    "0.00884490415465248",
    "0.0001009279278349384",
    "10.25746491784498",
)
_SEED3_PSI = "0.5324177893726738,0.7932312298914563,0.900316999333693,{},0.6587029436416691,0.8181714107945728,0.8762549752454494"
_SEED2 = (
    "1.0816194026170879e-10,9.562720802221059e-11,9.380987550453708e-11",
    "0.007858357937557346",
    "0.00012323127752031612",
    "8.902411665340848",
)
_SEED2_PSI = "0.6167321346094314,0.477924874564142,0.5050480703412692,0.5116023452183369,0.99,0.8341906082956223,0.5631344076349061"
_DIAGNOSTICS = (
    _diagnostic(3, "seed3_control", *_SEED3, _SEED3_PSI.format("0.9999979999999999")),
    _diagnostic(3, "seed3_start099", *_SEED3, _SEED3_PSI.format("0.99")),
    _diagnostic(2, "seed2_start099", *_SEED2, _SEED2_PSI),
)

_SIGMA_SWEEP = "python -m experiments.papers.p000.sigma_sweep --out outputs/p000_sigma_sweep/rows.csv"
_UKF_ONLY = "filter=p002_ukf 'learn=[Q,R]' '~experiment.hand_tuned.rho'"

#: Output folder of the reruns with seeded starts of bounded parameters perturbed in logit space
#: (results/p00_bounded_starts.md): they reproduce the current code's numbers of the families that
#: learn a bounded value; the original rows of those families came from the old clamped starts
#: (reproducible at commit 169863d, where the same commands wrote outputs/sweeps, outputs/final).
RERUN = "outputs/rerun_logit"

#: Every job behind the results/p00*.md numbers that the current code reproduces (CPU seconds: for
#: the 24 jobs that finished in the quiet rerun of 2026-12-07 its measured figures, cold kernel cache
#: included (results/data/reproduce_times_2026-12-07.tsv); for the others, those measured when they
#: were produced: results/p00_compute_budget.md, the reruns' own timings).
JOBS: tuple[Job, ...] = (
    Job("p000_infamily", "p000_gpsdr.md", 212, (_final("p000_infamily", "p000_infamily"),)),
    Job("p000_gyro", "p000_gpsdr.md", 103, (_final("p000_gpsdr", "p000_gyro", "scenario=p000_gyro"),)),
    Job("p000_gps", "p000_gpsdr.md", 104, (_final("p000_gpsdr", "p000_gps", "scenario=p000_gps"),)),
    Job("p000_odometer", "p000_gpsdr.md", 152, (_final("p000_gpsdr", "p000_odometer", "scenario=p000_odometer"),)),
    Job("p000_nominal", "p000_gpsdr.md", 97, (_final("p000_gpsdr", "p000_nominal", "scenario=p000_random"),)),
    Job("p000_sigma_sweep", "p000_gpsdr.md", 290, (_SIGMA_SWEEP,)),
    Job("p001_colored", "p001_colored.md", 255, _sweep("p001_colored", RERUN)),
    Job("p001_multipath", "p001_multipath.md", 281, _sweep_and_test("p001_multipath", RERUN)),
    Job("p001_multipath_shared", "p001_multipath.md", 278, _sweep_and_test("p001_multipath_shared", RERUN, learned_values=False)),
    Job("p001_multipath_diagnostics", "p001_multipath.md", 261, _DIAGNOSTICS),
    Job("p001_elevation", "p001_elevation.md", 293, _sweep_and_test("p001_elevation", RERUN)),
    Job(
        "p002_infamily",
        "p002_pdr.md",
        160,
        (
            _final("p002_infamily", "p002_infamily", root=RERUN),
            *_summary_copy(f"{RERUN}/p002_infamily", f"{RERUN}/p002_infamily_exactref", "oracle='exact UKF'"),
        ),
    ),
    Job(
        "p002_disturbed",
        "p002_pdr.md",
        328,
        (
            _final("p002_pdr", "p002_disturbed_ukf", f"scenario=p002_disturbed {_UKF_ONLY}"),
            _final("p002_pdr", "p002_disturbed_rcukf", "scenario=p002_disturbed", root=RERUN),
            f"python -m experiments.papers.p002.report {RERUN}/p002_disturbed_rcukf",
        ),
    ),
    Job(
        "p002_pdr",
        "p002_pdr.md",
        344,
        (
            _final("p002_pdr", "p002_pdr_ukf", f"scenario=p002_pdr {_UKF_ONLY}"),
            _final("p002_pdr", "p002_pdr_rcukf", "scenario=p002_pdr", root=RERUN),
            f"python -m experiments.papers.p002.report {RERUN}/p002_pdr_rcukf outputs/final/p002_pdr_ukf",
            f"python -m experiments.papers.p002.report --between outputs/final/p002_pdr_ukf {RERUN}/p002_pdr_rcukf",
        ),
    ),
    Job("p003_modes", "p003_imm_sins.md", 604, _p003("p003_modes")),
    Job("p003_physical", "p003_imm_sins.md", 595, _p003("p003_physical")),
    Job("p003_imm_sins", "p003_imm_sins.md", 627, _p003("p003_imm_sins")),
    Job("p004_blend", "p004_blend.md", 250, _sweep("p004_blend", RERUN, learned_values=False)),
    Job(
        "p004_outage",
        "p004_blend.md",
        298,
        (
            *_sweep("p004_outage", RERUN, learned_values=False),
            *_summary_copy(f"{RERUN}/p004_outage", f"{RERUN}/p004_outage_vs_ukf", "reference='ukf'"),
            *_indist("p004_outage", RERUN),
        ),
    ),
    Job("p004_mems", "p004_mems.md", 302, _sweep_and_test("p004_mems", RERUN, learned_values=False)),
    Job("p004_urban", "p004_urban.md", 321, _sweep_and_test("p004_urban", RERUN, learned_values=False)),
    # issue 25: the families again with the practitioners' rows (results/p00_practitioners.md)
    Job("p001_elevation_practitioners", "p00_practitioners.md", 700, _practitioners("p001_elevation")),
    # (rerun at px000k's code state, whose learned row no longer matched the 11-27 one: 213 CPU-s, /usr/bin/time)
    Job("p000_infamily_practitioners", "p00_practitioners.md", 213, _practitioners("p000_infamily")),
    # cpu_s not measured (the five seeds took 6 min wall on the compiled engine; learned training 10.7 CPU-s per seed)
    Job("p000_gyro_practitioners", "p00_practitioners.md", 200, _practitioners("p000_gyro")),
    Job("p000_gps_practitioners", "p00_practitioners.md", 359, _practitioners("p000_gps")),
    Job("p000_nominal_practitioners", "p00_practitioners.md", 354, _practitioners("p000_nominal")),
    Job("p000_odometer_practitioners", "p00_practitioners.md", 374, _practitioners("p000_odometer")),
    Job("p001_colored_practitioners", "p00_practitioners.md", 529, _practitioners("p001_colored")),
    Job("p001_multipath_practitioners", "p00_practitioners.md", 468, _practitioners("p001_multipath")),
    Job("p001_multipath_shared_practitioners", "p00_practitioners.md", 458, _practitioners("p001_multipath_shared")),
    Job("p004_urban_practitioners", "p00_practitioners.md", 370, _practitioners("p004_urban")),
    Job("p004_mems_practitioners", "p00_practitioners.md", 349, _practitioners("p004_mems")),
    Job("p004_blend_practitioners", "p00_practitioners.md", 204, _practitioners("p004_blend")),
    # cpu_s not measured for this one (10.5 min wall on the loaded 2-core machine, compiled engine); it orders the queue only
    Job("p004_outage_practitioners", "p00_practitioners.md", 300, _practitioners("p004_outage")),
    # p003_physical: 973 CPU-s measured (/usr/bin/time, 5 seeds, 51 min wall on the loaded machine; eager engine);
    # 995 in the stopped rerun of 2026-11-28 (results/p00_compute_budget.md)
    Job("p003_physical_practitioners", "p00_practitioners.md", 1084, _practitioners("p003_physical")),
    # p003_modes / p003_imm_sins: 926 / 866 CPU-s measured (/usr/bin/time, 5 seeds, 30 / 27 min wall, the two side by side);
    # p003_modes 1,074 in the stopped rerun of 2026-11-28
    Job("p003_modes_practitioners", "p00_practitioners.md", 1119, _practitioners("p003_modes")),
    Job("p003_imm_sins_practitioners", "p00_practitioners.md", 1065, _practitioners("p003_imm_sins")),
    Job(
        "p002_disturbed_practitioners",
        "p00_practitioners.md",
        363,
        (
            "python experiments/train.py -m experiment=p002_disturbed_practitioners seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/practitioners/p002_disturbed_rcukf",
            "python -m experiments.practitioners outputs/practitioners/p002_disturbed_rcukf",
        ),
    ),
    Job(
        "p002_pdr_practitioners",
        "p00_practitioners.md",
        150,
        (
            "python experiments/train.py -m experiment=p002_pdr_practitioners seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/practitioners/p002_pdr_rcukf",
            "python -m experiments.practitioners outputs/practitioners/p002_pdr_rcukf",
        ),
    ),
    Job(
        "p002_infamily_exactref_practitioners",
        "p00_practitioners.md",
        186,
        (
            "python experiments/train.py -m experiment=p002_infamily_practitioners seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/practitioners/p002_infamily_exactref",
            "python -m experiments.practitioners outputs/practitioners/p002_infamily_exactref --oracle 'exact UKF'",
        ),
    ),
    # issue 25: the learned adaptive rows (results/p00_practitioners.md, "Learned adaptive"), joined to the
    # committed practitioners' data files (--collect joins them again after copying a practitioners summary)
    Job(
        "p001_elevation_learned_adaptive",
        "p00_practitioners.md",
        536,
        _learned_adaptive("p001_elevation_learned_adaptive", "p001_elevation"),
    ),
    Job("p004_urban_learned_adaptive", "p00_practitioners.md", 307, _learned_adaptive("p004_urban_learned_adaptive", "p004_urban")),
    Job(
        "p002_disturbed_learned_adaptive",
        "p00_practitioners.md",
        188,
        _learned_adaptive("p002_disturbed_learned_adaptive", "p002_disturbed_rcukf"),
    ),
    # ("Learned adaptive, more families", session la25b)
    Job("p004_mems_learned_adaptive", "p00_practitioners.md", 177, _learned_adaptive("p004_mems_learned_adaptive", "p004_mems")),
    Job("p004_blend_learned_adaptive", "p00_practitioners.md", 168, _learned_adaptive("p004_blend_learned_adaptive", "p004_blend")),
    Job("p004_outage_learned_adaptive", "p00_practitioners.md", 154, _learned_adaptive("p004_outage_learned_adaptive", "p004_outage")),
    Job("p002_pdr_learned_adaptive", "p00_practitioners.md", 142, _learned_adaptive("p002_pdr_learned_adaptive", "p002_pdr_rcukf")),
    # (session px25: p002_infamily_exactref, declared in "p002_infamily_exactref")
    Job(
        "p002_infamily_exactref_learned_adaptive",
        "p00_practitioners.md",
        174,
        _learned_adaptive("p002_infamily_learned_adaptive", "p002_infamily_exactref"),
    ),
    # (session px25: declared in "p003 learned adaptive"; 758 CPU-s measured, /usr/bin/time, 5 seeds, eager engine)
    Job(
        "p003_physical_learned_adaptive",
        "p00_practitioners.md",
        950,
        _learned_adaptive("p003_physical_learned_adaptive", "p003_physical"),
    ),
    Job("p003_modes_learned_adaptive", "p00_practitioners.md", 1006, _learned_adaptive("p003_modes_learned_adaptive", "p003_modes")),
    # (declared in "p003 learned adaptive"; run by the lead at 488a2e7 after that declaration's start deadline: 633 CPU-s)
    Job(
        "p003_imm_sins_learned_adaptive",
        "p00_practitioners.md",
        950,
        _learned_adaptive("p003_imm_sins_learned_adaptive", "p003_imm_sins"),
    ),
    # ("Learned adaptive, remaining families", session la25c)
    Job("p001_colored_learned_adaptive", "p00_practitioners.md", 313, _learned_adaptive("p001_colored_learned_adaptive", "p001_colored")),
    Job(
        "p001_multipath_learned_adaptive",
        "p00_practitioners.md",
        322,
        _learned_adaptive("p001_multipath_learned_adaptive", "p001_multipath"),
    ),
    Job(
        "p001_multipath_shared_learned_adaptive",
        "p00_practitioners.md",
        308,
        _learned_adaptive("p001_multipath_shared_learned_adaptive", "p001_multipath_shared"),
    ),
    # no job for p000_nominal / odometer / gps / gyro
    # (every seed's training diverged: the sweep exits non-zero, no row) nor p000_infamily (seed 2 diverged,
    # the join refused the 4-seed rows): the overlays stay for a rerun under a new declaration
    # ("Adaptive rows around a kappa 0 UKF", session px000k): the kappa 0 rows merged, then the learned adaptive
    # filter around the kappa 0 UKF joined; CPU-s measured (/usr/bin/time, user + sys, the two sweeps of each job)
    Job("p000_gyro_k0", "p00_practitioners.md", 423, _kappa0("p000_gyro")),
    Job("p000_gps_k0", "p00_practitioners.md", 264, _kappa0("p000_gps")),
    Job("p000_odometer_k0", "p00_practitioners.md", 312, _kappa0("p000_odometer")),
    Job("p000_nominal_k0", "p00_practitioners.md", 274, _kappa0("p000_nominal")),
    Job("p000_infamily_k0", "p00_practitioners.md", 352, _kappa0("p000_infamily")),
    # issue 25: data efficiency (N = 1, 4, 16 training trajectories) and transfer across p002's
    # families (results/p00_efficiency_transfer.md); the transfer pairs read all three p002 sweeps
    # 449 CPU-s in the stopped rerun of 2026-11-28 (1,500 when its results were produced, eager, loaded)
    Job(
        "p002_efficiency_transfer",
        "p00_efficiency_transfer.md",
        559,
        (
            "python experiments/train.py -m experiment=p002_pdr_efficiency data.train_size=1,4,16 seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/efficiency/p002_pdr",
            "python experiments/train.py -m experiment=p002_disturbed_transfer seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/transfer/p002_disturbed",
            "python experiments/train.py -m experiment=p002_infamily_transfer seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/transfer/p002_infamily",
            "python -m experiments.efficiency_transfer efficiency outputs/efficiency/p002_pdr --select test=pdr-P0.4 "
            "--out outputs/efficiency/p002_pdr/efficiency.csv",
            "python -m experiments.efficiency_transfer transfer --root outputs --out outputs/transfer/p002_transfer.csv",
        ),
    ),
    Job(
        "p000_infamily_efficiency",
        "p00_efficiency_transfer.md",
        428,
        (
            "python experiments/train.py -m experiment=p000_infamily_efficiency data.train_size=1,4,16 seed=0,1,2,3,4 logger=csv "
            "hydra.sweep.dir=outputs/efficiency/p000_infamily",
            "python -m experiments.efficiency_transfer efficiency outputs/efficiency/p000_infamily "
            "--out outputs/efficiency/p000_infamily/efficiency.csv",
        ),
    ),
)


def select_jobs(only: Sequence[str] | None = None, jobs: Sequence[Job] = JOBS) -> list[Job]:
    """The jobs whose name starts with one of ``only`` (all when empty), longest (by ``cpu_s``) first.

    Raises:
        ValueError: a prefix of ``only`` matches no job.
    """
    chosen = list(jobs)
    if only:
        for prefix in only:
            if not any(j.name.startswith(prefix) for j in jobs):
                raise ValueError(f"--only: {prefix!r} matches no job (jobs: {', '.join(j.name for j in jobs)})")
        chosen = [j for j in jobs if any(j.name.startswith(p) for p in only)]
    return sorted(chosen, key=lambda j: -j.cpu_s)


def _run(job: Job, out: Path) -> tuple[Job, int, float, float]:
    """Run ``job``'s commands in one shell; return (job, exit status, wall s, CPU s of the shell and its children)."""
    script = "set -e\n" + "\n".join(job.commands) + "\n"
    with open(out / f"{job.name}.log", "w") as log:
        start = time.perf_counter()
        proc = subprocess.Popen(["bash", "-c", script], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - start
    return job, proc.returncode, wall, usage.ru_utime + usage.ru_stime


def main(argv: Sequence[str] | None = None, jobs: Sequence[Job] = JOBS) -> int:
    """Command-line entry point (``jobs``: the job table, replaced in tests); returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-j", "--jobs", type=int, default=2, help="jobs at a time (default 2: one per core)")
    parser.add_argument("--only", nargs="+", default=None, help="job name prefixes (default: every job)")
    parser.add_argument("--out", type=Path, default=Path("outputs/reproduce"), help="logs and times.tsv (default outputs/reproduce)")
    parser.add_argument("--dry-run", action="store_true", help="print the jobs' commands and stop")
    parser.add_argument("--collect", action="store_true", help="after every job succeeded: summary.csv -> results/data, render, check")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"-j/--jobs must be a positive integer, got {args.jobs}")
    try:
        jobs = select_jobs(args.only, jobs)
    except ValueError as err:
        parser.error(str(err))
    if args.dry_run:
        for job in jobs:
            print(f"# {job.name} (results/{job.results}, ~{job.cpu_s:.0f} CPU s when recorded)")
            print("\n".join(job.commands))
        print(f"# {len(jobs)} jobs, ~{sum(j.cpu_s for j in jobs) / 60:.0f} CPU min when recorded")
        return 0
    out = args.out if args.out.is_absolute() else ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    failed: list[str] = []
    start = time.perf_counter()
    cpu_total = 0.0
    with open(out / "times.tsv", "a") as times, ThreadPoolExecutor(max_workers=args.jobs) as pool:
        times.write("job\tstatus\twall_s\tcpu_s\n")
        for job, status, wall, cpu in pool.map(lambda j: _run(j, out), jobs):
            cpu_total += cpu
            times.write(f"{job.name}\t{status}\t{wall:.1f}\t{cpu:.1f}\n")
            times.flush()
            print(f"{job.name}: {'ok' if status == 0 else f'FAILED ({status})'}, wall {wall:.0f} s, CPU {cpu:.0f} s", flush=True)
            if status:
                failed.append(job.name)
    wall = time.perf_counter() - start
    summary = f"all\t{len(failed)} failed\t{wall:.1f}\t{cpu_total:.1f}\n"
    with open(out / "times.tsv", "a") as times:
        times.write(summary)
    print(f"{len(jobs)} jobs, {args.jobs} at a time: wall {wall / 60:.1f} min, CPU {cpu_total / 60:.1f} min; logs in {out}")
    if failed:
        print(f"failed: {', '.join(failed)} (see {out}/<job>.log)", file=sys.stderr)
        return 1
    if args.collect:
        copied = results_report.collect(ROOT)
        results_report.render(ROOT)
        problems = results_report.check(ROOT)
        print(f"collected {len(copied)} summary.csv into results/data; results check: {len(problems)} problem(s)")
        for p in problems:
            print(p, file=sys.stderr)
        return 1 if problems else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
