"""``dks-gym reproduce``: run the experiments of the paper's Section IV for one benchmark, write their tables
and figures.

The experiments are the objects of :data:`~dks_gym.evaluation.experiment.EXPERIMENTS` (the paper's, in
:mod:`~dks_gym.evaluation.paper_experiments`); this module runs what they ask for and assembles what they
draw. Models come from :func:`dks_gym.models.load_model` (trained when missing unless ``train=False``, so a
rerun reuses every finished or resumes every interrupted training). Identical runs requested by several
experiments are computed once. The output folder gets ``results.json.gz`` (schema in
:mod:`dks_gym.evaluation.results`; the records of experiments not rerun are kept from an existing file for
the same benchmark, preset, dataset and protocol; the file names the benchmark's protocol and marks the
records that leave it, :mod:`dks_gym.evaluation.conformance`), ``tables.md`` (ours beside the paper's numbers) and
``figures/*.png``.
"""

from __future__ import annotations

import concurrent.futures as cf
import platform
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from ..assimilation import AssimilationConfig, AssimilationResult, run_assimilation, tune_if_missing
from ..assimilation.config import PAPER_P0, PAPER_Q
from ..benchmarks.protocol import get_protocol
from ..dataset import Dataset
from ..models import LatentModel
from ..parallel import map_tasks
from .conformance import PROTOCOL_KEY, stamp_protocol
from .experiment import EXPERIMENTS, Run, Section
from .figures import MODEL_LABELS
from .formatting import fixed, markdown_table, sci
from .paper_experiments import MODELS
from . import parameter_experiment  # noqa: F401,E402  (registers `parameter` after the paper's experiments)
from .results import (
    RESULTS_FILE,
    Record,
    ResultsDocument,
    ResultsError,
    load_results,
    make_record,
    merge,
    new_results,
    record_key,
    save_results,
)
from .tabulate import Records


def plan(only: Iterable[str] | None = None, models: Iterable[str] | None = None) -> list[tuple[str, Run]]:
    """(experiment, run) pairs of the selected experiments (all by default), in :data:`EXPERIMENTS` order,
    restricted to the runs of ``models`` (default: all four)."""
    chosen = list(EXPERIMENTS) if not only else list(dict.fromkeys(only))
    for name in chosen:
        if name not in EXPERIMENTS:
            raise ValueError(f"unknown experiment {name!r}; choose from {', '.join(EXPERIMENTS)}")
    kinds = set(MODELS if not models else models)
    if kinds - set(MODELS):
        raise ValueError(f"unknown model(s) {', '.join(sorted(kinds - set(MODELS)))}; choose from {', '.join(MODELS)}")
    return [(name, run) for name in chosen for run in EXPERIMENTS[name].runs() if run.model in kinds]


# Tables and figures ----------------------------------------------------------------------------------------
def _models_section(doc: ResultsDocument) -> list[Section]:
    """The trained models the runs used: size, training, one-step error against persistence."""
    if not doc.get("models"):
        return []
    rows = [[MODEL_LABELS.get(m["model"], m["model"]), str(m["r"]), str(m["T"]), m.get("preset") or "-",
             str(m.get("steps") if m.get("steps") is not None else "-"), fixed(m.get("train_time_s"), 0),
             sci(m.get("one_step_test_mse")), sci(m.get("persistence_test_mse"))] for m in doc["models"]]
    return [Section("Models", (markdown_table(["model", "r", "T", "preset", "steps", "train time [s]",
                                               "one-step test MSE", "persistence MSE"], rows),))]


def tables_markdown(doc: ResultsDocument) -> str:
    """Markdown tables of every experiment present in ``doc``, with the paper's numbers where it gives them."""
    bench, cfg, records = doc["benchmark"], doc["config"], Records(doc)
    blocks = [
        f"# dks-gym reproduce: {bench} (model preset `{doc['preset']}`)",
        (f"Final-time MSE (Eq. 18, physical units, scored channels {', '.join(cfg.get('scored_channels', []))}) "
         f"over the {cfg.get('n_test')} test trajectories: mean ± sample std. m = {cfg.get('n_sensors')} sensors "
         f"on `{cfg.get('observed_channel')}`, Q = {cfg.get('Q')} I, P0 = {cfg.get('P0')} I, noise seed "
         f"{cfg.get('noise_seed')}; r = 32, T = 1, 20% noise, approximate initial condition unless stated. "
         f"Data: `{Path(str(doc['dataset'].get('path'))).name}` (preset {doc['dataset'].get('preset')}, sha256 "
         f"fingerprint {str(doc['dataset'].get('fingerprint'))[:12]}). Created "
         f"{cfg.get('created')} on {cfg.get('device')} with dks-gym {cfg.get('dks_gym_version')}."),
    ]
    if bench != "burgers":
        blocks.append("The paper's CFD data are not specified exactly enough to compare absolute numbers: "
                      "compare orderings and ratios.")
    sections = _models_section(doc)
    sections += [s for e in EXPERIMENTS.values() if e.present(records) for s in e.tables(records)]
    return "\n\n".join(blocks + [s.markdown() for s in sections]) + "\n"


def write_figures(doc: ResultsDocument, folder: str | Path, *, cache: dict[tuple, AssimilationResult] | None = None,
                  dataset: Dataset | None = None) -> list[Path]:
    """The paper's figures for every experiment present in ``doc`` (reconstructions need this run's ``cache``)."""
    records = Records(doc)
    return [path for e in EXPERIMENTS.values() if e.present(records)
            for path in e.figures(records, Path(folder), cache, dataset)]


# Running ---------------------------------------------------------------------------------------------------
def _dataset(benchmark: str, data_preset: str, dataset: Dataset | str | Path | None, progress: bool,
             log: Callable[[str], None]) -> Dataset:
    from ..dataset import DatasetMissing, generate_dataset, load_dataset

    if dataset is not None:
        return dataset if isinstance(dataset, Dataset) else Dataset(dataset)
    try:
        return load_dataset(benchmark, data_preset)
    except DatasetMissing:
        log(f"dks-gym: no {benchmark} {data_preset} dataset yet; generating it")
        return load_dataset(benchmark, data_preset, generate_dataset(benchmark, data_preset, progress=progress))


def _model_info(model: LatentModel, kind: str, r: int, T: int, preset: str, dataset: Dataset) -> dict[str, Any]:
    from ..models.checkpoint import checkpoint_path, read_metadata
    from ..models.diagnostics import one_step_error

    path = getattr(model, "checkpoint_path", None) or checkpoint_path(
        dataset.benchmark.name, kind, preset, r, T, data_preset=dataset.preset or "custom")
    meta = read_metadata(path) if Path(path).exists() else {}
    info = {"model": kind, "r": r, "T": T, "preset": "" if model.fitted_in_closed_form else preset,
            "checkpoint": str(path),
            "steps": meta.get("steps_done"), "batch_size": meta.get("batch_size"),
            "train_time_s": meta.get("train_time_s"), "train_device": meta.get("device")}
    err = one_step_error(model, dataset, "test")
    info.update(one_step_test_mse=err["model_mse"], persistence_test_mse=err["persistence_mse"])
    return info


def _prepared_model(benchmark: str, key: tuple[str, int, int], preset: str, dataset: Dataset, device: str,
                    train: bool, progress: bool) -> tuple[LatentModel, dict[str, Any]]:
    """Task: the model ``key`` (kind, r, T), trained and tuned here when missing and ``train`` (each training
    under its checkpoint's lock), and its entry of the results file's ``models``."""
    from ..models import load_model

    kind, r, T = key
    model = load_model(benchmark, kind, r=r, preset=preset, T=T, dataset=dataset, device=device,
                       train_if_missing=train, progress=progress)
    if train:  # a model trained here is tuned here too (Q="calibrated" needs its scale)
        tune_if_missing(model, dataset, progress=progress)
    return model, _model_info(model, kind, r, T, preset, dataset)


def _assimilate(model: LatentModel, dataset: Dataset, config: AssimilationConfig, single: bool, calibrated: bool,
                description: str, progress: bool) -> AssimilationResult:
    """Task: one batched run of :func:`run_assimilation` over the test split (``single``: its first trajectory)."""
    # The predictive std (r decoder JVPs per step) is scored where it is reported: the calibrated filters.
    # The paper's experiments compare errors only, and on the CFD grids the std would triple their cost.
    return run_assimilation(model, dataset, config, trajectories=[0] if single else None, progress=progress,
                            description=description, uncertainty=calibrated)


def _trained(benchmark: str, key: tuple[str, int, int], preset: str, dataset: Dataset) -> bool:
    """Whether ``load_model`` finds model ``key`` (kind, r, T) without training (:func:`locate_model`)."""
    from ..models.lookup import locate_model

    kind, r, T = key
    return locate_model(benchmark, kind, r, preset, T, dataset=dataset).found is not None


def _previous(path: Path, benchmark: str, preset: str, identity: dict[str, Any]) -> ResultsDocument | None:
    """An existing results file in the output folder, if it can be extended by this run (else a clear error)."""
    if not path.exists():
        return None
    doc = load_results(path)
    if (doc["benchmark"], doc["preset"]) != (benchmark, preset) or \
            doc["dataset"].get("fingerprint") != identity.get("fingerprint"):
        raise ResultsError(
            f"{path} holds results for {doc['benchmark']} / preset {doc['preset']} on dataset "
            f"{doc['dataset'].get('path')}, which cannot be combined with this run ({benchmark} / preset {preset} on "
            f"{identity.get('path')}); choose another --out or remove the file"
        )
    ours = get_protocol(benchmark)
    theirs = doc.get(PROTOCOL_KEY)
    # a file written before protocols holds runs made as dks-v1 v1 prescribes: it is extended and stamped
    if theirs is not None and (theirs.get("name"), theirs.get("version")) != (ours.name, ours.version):
        raise ResultsError(f"{path} holds results of protocol {theirs.get('name')} v{theirs.get('version')}, not "
                           f"{ours.name} v{ours.version}; choose another --out or remove the file")
    return doc


def shared_config(base: AssimilationConfig, ds: Dataset, device: str) -> dict[str, Any]:
    """What every record of a run with the filter settings ``base`` on ``ds`` shares, for a results file's
    ``config`` (reproduce's and the demo's): sensors, P0, Q, seeds, split, the data, device and versions."""
    import torch

    from ..version import __version__

    return {
        "n_sensors": base.n_sensors, "P0": base.filter.P0, "Q": base.filter.Q, "noise_seed": base.noise_seed,
        "filter_seed": base.filter.seed, "split": base.split, "n_test": ds.n_trajectories(base.split),
        "n_frames": ds.n_frames, "dt": ds.dt, "t0": float(ds.time[0]), "param_name": ds.param_name,
        "observed_channel": ds.observed_channel, "scored_channels": list(ds.scored_channels),
        "device": str(device), "dtype": "float32", "data_preset": ds.preset, "dks_gym_version": __version__,
        "torch_version": torch.__version__, "python": platform.python_version(),
    }


@dataclass
class Reproduction:
    """One ``reproduce`` call's state: what it runs on, what it keeps, and what it has done so far."""

    benchmark: str
    preset: str
    device: str
    out: Path
    dataset: Dataset
    identity: dict[str, Any]
    base: AssimilationConfig  # the paper's P0 and Q; the calibrated experiment replaces both per run
    config: dict[str, Any]  # the results file's shared config
    previous: ResultsDocument | None  # the results already in the output folder, merged into ours
    kept: dict[tuple, Record]  # records of previous kept instead of rerun (skip_done)
    train: bool
    progress: bool
    start: float = field(default_factory=time.perf_counter)
    models: dict[tuple[str, int, int], LatentModel] = field(default_factory=dict)
    infos: list[dict[str, Any]] = field(default_factory=list)
    results: dict[tuple, AssimilationResult] = field(default_factory=dict)  # by Run.cache_key
    records: list[Record] = field(default_factory=list)
    doc: ResultsDocument | None = None
    pending: Iterator[tuple[tuple, AssimilationResult]] = field(default_factory=lambda: iter(()))

    def prepare(self, keys: Iterable[tuple[str, int, int]], executor: cf.Executor | None = None) -> None:
        """Load the models (kind, r, T) of ``keys``, in order, each once: trained when missing (and allowed),
        independent trainings spread over ``executor`` (:func:`~dks_gym.parallel.map_tasks`)."""
        keys = [key for key in dict.fromkeys(keys) if key not in self.models]
        tasks = [(self.benchmark, key, self.preset, self.dataset, self.device, self.train,
                  self.progress and executor is None) for key in keys]
        for key, (model, info) in zip(keys, map_tasks(_prepared_model, tasks, executor)):
            self.models[key] = model
            self.infos.append(info)

    def computations(self, todo: Iterable[Run], executor: cf.Executor | None = None) -> None:
        """Start the distinct computations of the runs ``todo`` (experiments repeat identical runs), in order of
        first need, spread over ``executor``; :meth:`run` takes their results in that order."""
        first: dict[tuple, Run] = {}
        for run in todo:
            if run.cache_key not in self.results:
                first.setdefault(run.cache_key, run)
        runs = list(first.values())
        self.prepare([run.model_key for run in runs], executor)
        tasks = [(self.models[run.model_key], self.dataset, self._config(run), run.single, run.calibrated,
                  f"{run.model} {run.filter}", self.progress and executor is None) for run in runs]
        self.pending = zip([run.cache_key for run in runs], map_tasks(_assimilate, tasks, executor))

    def _config(self, run: Run) -> AssimilationConfig:
        config = self.base.replace(kind=run.filter, initial=run.initial, noise_level=run.noise,
                                   n_members=run.n_members, parameter=run.parameter)
        return config.replace(Q="calibrated", P0="calibrated") if run.calibrated else config

    def run(self, experiment: str, run: Run) -> None:
        """Add the record of ``run`` for ``experiment`` (kept, or computed by :meth:`computations`, whose results
        arrive in order), then rewrite the results and tables."""
        if run.record_key(experiment) in self.kept:
            self.records.append(self.kept[run.record_key(experiment)])
            return
        if run.cache_key not in self.results:
            key, result = next(self.pending)
            if key != run.cache_key:  # pragma: no cover - computations() orders them as the runs ask
                raise RuntimeError(f"the runs arrived out of order: {key} instead of {run.cache_key}")
            self.results[key] = result
        self.records.append(make_record(self.results[run.cache_key], experiment=experiment, T=run.T,
                                        keep_curves=experiment == "main"))
        self.save()

    def save(self) -> None:
        """Write results.json.gz (the records so far, plus the experiments of ``previous`` not in them), tables.md."""
        stamp = {"created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                 "wall_time_s": time.perf_counter() - self.start}
        doc = new_results(self.benchmark, self.preset, self.identity, dict(self.config, **stamp), self.records,
                          self.infos)
        if self.previous is not None:
            doc = merge(self.previous, doc)
        present = {r["experiment"] for r in doc["records"]}
        doc["config"]["experiments"] = [n for n in EXPERIMENTS if n in present]
        stamp_protocol(doc)
        save_results(doc, self.out / RESULTS_FILE)
        (self.out / "tables.md").write_text(tables_markdown(doc))
        self.doc = doc


def _open(benchmark: str, preset: str, device: str, out: Path, ds: Dataset, train: bool, skip_done: bool,
          noise_seed: int, filter_seed: int, progress: bool) -> Reproduction:
    """The state of a reproduce run: the dataset's identity, the results already in ``out``, the shared config."""
    from ..models.checkpoint import dataset_identity

    identity = dataset_identity(ds)
    previous = _previous(out / RESULTS_FILE, benchmark, preset, identity)
    # With skip_done, a run whose record is already in the results file is kept, not rerun: an interrupted
    # reproduce continues where it stopped (records are saved after every run, checkpoints during training).
    kept = {record_key(r): r for r in previous["records"]} if skip_done and previous is not None else {}
    # The paper's P0 and Q for its tables (the values the committed results record).
    base = AssimilationConfig(noise_seed=noise_seed).replace(seed=filter_seed, P0=PAPER_P0, Q=PAPER_Q)
    return Reproduction(benchmark, preset, device, out, ds, identity, base,
                        shared_config(base, ds, device), previous, kept, train, progress)


def _announce(session: Reproduction, pairs: list[tuple[str, Run]], log: Callable[[str], None]) -> int:
    """Log how many runs are left and which models must be trained first; return the number left."""
    todo = [(name, run) for name, run in pairs if run.record_key(name) not in session.kept]
    if len(todo) < len(pairs):
        log(f"dks-gym: skipping experiments already in {session.out / RESULTS_FILE} ({len(pairs) - len(todo)} "
            f"of {len(pairs)} runs kept; an experiment interrupted part way continues with its missing runs)")
    missing = sorted({"{} r={} T={}".format(*run.model_key) for _, run in todo
                      if not _trained(session.benchmark, run.model_key, session.preset, session.dataset)})
    log(f"dks-gym: {len(todo)} runs to do" + (f"; {len(missing)} models to train first ({', '.join(missing)})"
                                              if missing and session.train else ""))
    return len(todo)


def reproduce(
    benchmark: str,
    *,
    preset: str = "lite",
    device: str = "cpu",
    out: str | Path | None = None,
    only: Iterable[str] | None = None,
    models: Iterable[str] | None = None,
    data_preset: str = "paper",
    dataset: Dataset | str | Path | None = None,
    train: bool = True,
    skip_done: bool = False,
    noise_seed: int = 0,
    filter_seed: int = 0,
    progress: bool = True,
    log: Callable[[str], None] = print,
    executor: cf.Executor | None = None,
) -> ResultsDocument | dict[str, Any]:
    """Run the selected experiments, write results.json.gz, tables.md and figures to ``out``; return the results.

    Experiments run one after the other; after every run the results file and the tables are rewritten, so
    an interrupted run keeps every finished run (and every finished or partial training). ``skip_done``
    keeps the runs already in ``out/results.json.gz`` instead of rerunning them: rerun with it to continue.
    Before starting it logs how many runs are left and which models must be trained first.

    ``executor`` (a process pool, ``distributed.Client.get_executor()``; default: this process) runs the
    independent trainings, then the filter runs, on its workers (:func:`~dks_gym.parallel.map_tasks`); their
    results are recorded in the same order as in a serial run, so the files are the same but for the
    measured times (the timing experiment's step times are measured beside the other workers' runs).
    """
    from tqdm.auto import tqdm

    benchmark = benchmark.lower()
    if preset not in ("lite", "paper"):
        raise ValueError(f"unknown model preset {preset!r}; choose 'lite' or 'paper'")
    pairs = plan(only, models)
    out = Path(out) if out is not None else Path("results") / f"{benchmark}-{preset}"
    ds = _dataset(benchmark, data_preset, dataset, progress, log)
    session = _open(benchmark, preset, device, out, ds, train, skip_done, noise_seed, filter_seed, progress)
    session.doc = session.previous
    left = _announce(session, pairs, log)
    session.computations([run for name, run in pairs if run.record_key(name) not in session.kept], executor)
    bar = tqdm(total=len(pairs), initial=len(pairs) - left, desc=f"reproduce {benchmark}", unit="run",
               disable=not progress, dynamic_ncols=True)
    for experiment, run in pairs:
        kept = run.record_key(experiment) in session.kept
        bar.set_postfix_str(f"{experiment}: {run.model} {run.filter} {run.initial}", refresh=False)
        session.run(experiment, run)
        bar.update(0 if kept else 1)
    bar.close()
    if not left and session.doc is not None:  # nothing ran: the file is complete already
        log("dks-gym: nothing left to run")
    elif session.doc is None:
        log("dks-gym: nothing to run")
        return {}
    write_figures(session.doc, out / "figures", cache=session.results, dataset=ds)
    log(f"dks-gym: wrote {out / RESULTS_FILE}, {out / 'tables.md'} and {out / 'figures'} "
        f"in {time.perf_counter() - session.start:.0f} s")
    return session.doc


__all__ = ["EXPERIMENTS", "Reproduction", "Run", "plan", "reproduce", "shared_config", "tables_markdown",
           "write_figures"]
