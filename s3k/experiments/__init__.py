"""``s3k experiment NAME --out DIR``: the paper's experiments as resumable sweeps, with a summary and plots.

Experiments (section numbers of Vecerik et al., CoRL 2020):

- ``label-efficiency`` (4.1): box scene; labelled x unlabelled frame counts; unlabelled 0 is the labels-only
  baseline (``--no-unsup``). Plots: error per labelled count (one curve per unlabelled count) and error
  against the total number of frames coloured by the labelled share.
- ``domain-shift`` (4.2): distractors scene, labels from the first distractor set only ("start") or spread
  over the whole timeline ("full"), over labelled and unlabelled counts; test on distractor sets never seen.
- ``category`` (4.3): category scene, trained on 1-12 instances, evaluated on the training instances (frames
  never labelled) and on the 4 held-out ones; compared with the paper's table (400 px, in millimetres).
- ``alpha`` (appendix C): weight of the self-supervised term at a few labelled counts.

Layout of ``DIR`` (one DIR can hold every experiment of one scale; they share the rendered data)::

    DIR/data/<pool>/                 a rendered dataset per (scene, mode, instances, size, frame counts, seed)
    DIR/data/views/<pool>/<view>/    a run's frames of a pool: its tables, images linked, not copied
    DIR/<experiment>/runs/<run>/     the training run folder (s3k.detector) and result.json once finished
    DIR/<experiment>/summary.json    per grid point: mean, std and values over seeds; findings; mm per px
    DIR/<experiment>/*.png, README.md

Resuming: a run with a ``result.json`` is never redone; a run killed during training continues from its last
checkpoint (``train(..., resume=True)``); a dataset is rendered into ``NAME.tmp`` and renamed when complete.
Several invocations on one DIR may run at the same time (e.g. one per core with ``--threads 1``): a run being
trained by a live process is skipped (a lock on ``run.lock``), a pool being rendered is waited for.

Two passes (``Options.two_pass``, ``--two-pass``): every run is trained coarse-to-fine as ``s3k train
--two-pass`` trains it (:mod:`s3k.train.two_pass`), from pools rendered larger than the coarse pass's
input; its run folder holds ``coarse/``, ``crops/`` and ``fine/``, and its pixel errors are in crop pixels.

Labelled frames: drawn at random, stratified (below), or with ``--label-choice coverage`` or
``representative`` as a labeller following one of the labelling app's pose rankings would pick them (over
the pool's true poses).

Seeds: run seed ``s`` trains with ``TrainConfig.seed = s`` on its own random choice of labelled frames from
the pool (nested: the first 3 of a seed's 10); the unlabelled and test frames do not depend on the seed, so
the runs of one grid point differ in the labelled frames and the initialization.

The modules: :mod:`~s3k.experiments.grid` (scales, grids, the plan), :mod:`~s3k.experiments.views` (pools,
frame choice, views), :mod:`~s3k.experiments.runner` (running and resuming), :mod:`~s3k.experiments.findings`
(statistics, the paper's claims), :mod:`~s3k.experiments.report` (summary.json, plots, README.md).
The benchmarks' stages live beside them, the scripts under ``benchmarks/`` parsing arguments over them:
:mod:`~s3k.experiments.accuracy` (S3K against labels only over seeds), :mod:`~s3k.experiments.poses` (error
by pose, labelled frames by pose) and :mod:`~s3k.experiments.label_clicks` (clicks per labelled frame).
"""

from s3k.experiments.findings import aggregate, findings, verdict
from s3k.experiments.grid import (
    DESCRIPTIONS,
    EXPERIMENTS,
    LABEL_CHOICES,
    PAPER_CATEGORY_TEST_PX,
    PAPER_MM_PER_PX,
    SCALES,
    SUMMARY_FILE,
    Options,
    PoolSpec,
    RunSpec,
    plan,
)
from s3k.experiments.report import publish, published, resummarize, summarize
from s3k.experiments.runner import describe_plan, run_experiment
from s3k.experiments.views import stratified_pick

__all__ = ["DESCRIPTIONS", "EXPERIMENTS", "LABEL_CHOICES", "PAPER_CATEGORY_TEST_PX", "PAPER_MM_PER_PX",
           "SCALES", "SUMMARY_FILE", "Options", "PoolSpec", "RunSpec", "aggregate", "describe_plan",
           "findings", "plan", "publish", "published", "resummarize", "run_experiment", "stratified_pick",
           "summarize", "verdict"]
