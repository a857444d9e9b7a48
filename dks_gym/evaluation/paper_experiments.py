"""The experiments of the paper's Section IV, one class each (runs, tables, figures), in the order they run.

All on the test split, m = 16 sensors, Q = 1e-4 I, P0 = I, one noise realization shared by every model and
filter; r = 32, T = 1, 20 % noise and the approximate initial condition unless an experiment varies one:

==============  ======================================================================  =================
name            runs                                                                    paper
==============  ======================================================================  =================
main            forward run and EKF, four models, approximate and exact initial state   Figs. 3, 5, 7, 8
enkf            forward run and EnKF (n = 20), four models                              Table VII, Fig. 12
calibrated      EKF and EnKF with Q and P0 from each model's own errors                 (not in the paper)
ensemble        EnKF with n = 20, 40, 64 for Koopman, MLP, xLSTM                         Table VIII
noise           forward run and EKF at 10% and 30% noise, four models                   Fig. 10
latent          forward run and EKF at r = 16 and 64, four models                       Fig. 11
multistep       forward run and EKF at T = 2, 4, 8, Koopman and MLP                     Fig. 13
operator_norm   max_k ||F_k||_2 of the EKF and forward runs, four models                Table IX
timing          wall time per DA step, one trajectory at a time (B = 1), every filter   Figs. 4, 6
==============  ======================================================================  =================

A new experiment is one more :func:`~dks_gym.evaluation.experiment.register`-ed class, here or anywhere.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..assimilation import AssimilationResult
from ..dataset import Dataset
from .claims import NEURAL, qualitative_checks
from .experiment import BarChart, Experiment, Run, Section, register
from .figures import MODEL_LABELS, MODEL_ORDER, reconstruction_figure, spread_figure, temporal_error_figure
from .figures import timing_figure
from .formatting import MISSING, fixed, percent, sci, sig
from .paper import PAPER_DERIVED, PAPER_ENSEMBLE, PAPER_MULTISTEP, PAPER_OPERATOR_NORM
from .results import Record
from .tabulate import DEFAULT_SCENARIO, Column, Records, Row, label, max_norm, mse, mse_ratio, over_steps
from .tabulate import mse_ci95, paper_mse, rel_l2, rel_l2_columns, tabulate

MODELS = MODEL_ORDER  # koopman, pdmd, mlp, xlstm
MODEL = Column("model", label)


# Figure helpers --------------------------------------------------------------------------------------------
def _panel(records: Records, title: str, base_criteria: dict[str, Any], **criteria: Any) -> tuple | None:
    """A bar-chart panel: the four models' records of a scenario and its MLP forward run (the normalization)."""
    base = records.base(**base_criteria)
    recs = [rec for m in MODELS if (rec := records.find(model=m, **criteria)) is not None]
    return (title, recs, base) if base is not None and recs and base["final_mse_mean"] else None


def _scenario(**changes: Any) -> dict[str, Any]:
    """The paper's default scenario with one thing varied."""
    return {**DEFAULT_SCENARIO, **changes}


# main --------------------------------------------------------------------------------------------------------
@register
class Main(Experiment):
    name = "main"
    description = "forward run vs EKF, four models, approximate and exact initial condition (Figs. 3, 5, 7, 8)"

    def runs(self) -> list[Run]:
        return [Run(m, f, i) for i in ("approximate", "exact") for f in ("forward", "ekf") for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        bench = records.benchmark
        sections = []
        for initial, fig in (("approximate", "Fig. 3"), ("exact", "Fig. 5")):
            base = records.base(experiment="main", initial=initial)
            rows = [{"model": m, "base": base, **{f: records.find(experiment="main", model=m, filter=f,
                                                                  initial=initial) for f in ("forward", "ekf")}}
                    for m in MODELS]
            columns = [MODEL, Column("forward run", lambda r: mse(r["forward"])),
                       Column("EKF", lambda r: mse(r["ekf"])), *rel_l2_columns({"forward": "forward", "ekf": "EKF"}),
                       Column("EKF IQM [95 % CI]", lambda r: mse_ci95(r["ekf"]), optional=True),
                       Column("EKF / forward", lambda r: mse_ratio(r["ekf"], r["forward"])),
                       Column("forward / MLP fwd", lambda r: mse_ratio(r["forward"], r["base"])),
                       Column("EKF / MLP fwd", lambda r: mse_ratio(r["ekf"], r["base"]))]
            if initial == "approximate":
                columns += [Column("paper forward", lambda r: paper_mse(bench, r["model"], "forward")),
                            Column("paper EKF", lambda r: paper_mse(bench, r["model"], "ekf"))]
            body = [tabulate(rows, columns)]
            if initial == "exact" and bench in PAPER_DERIVED:
                body.append("\n".join(f"`≈` {MODEL_LABELS[m]} {f.upper()}: {text}"
                                      for (m, f), (_, text) in PAPER_DERIVED[bench].items()))
            sections.append(Section(f"Main comparison, {initial} initial condition ({fig})", tuple(body)))
        checks = qualitative_checks(records)
        if checks:
            sections.append(Section("The paper's qualitative claims on this run", ("\n".join(
                f"- {'yes' if ok else 'NO' if ok is not None else 'n/a'}: {claim} ({evidence})"
                for claim, ok, evidence in checks),)))
        return sections + self._per_channel(records)

    def _per_channel(self, records: Records) -> list[Section]:
        """Each scored channel's error over its data variance, where a benchmark scores several."""
        channels = records.config.get("scored_channels", [])
        if len(channels) < 2:
            return []
        rows = [{"model": m, "filter": f, "rec": rec} for m in MODELS for f in ("forward", "ekf")
                if (rec := records.find(experiment="main", model=m, filter=f, initial="approximate"))
                and rec.get("final_channel_nmse_mean")]
        if not rows:
            return []
        columns = [MODEL, Column("estimate", lambda r: "forward run" if r["filter"] == "forward" else "EKF"),
                   *[Column(f"{c} (normalized)", lambda r, c=c: sci(r["rec"]["final_channel_nmse_mean"].get(c)))
                     for c in channels],
                   *[Column(f"{c} rel. L2", lambda r, c=c: percent((r["rec"].get("final_channel_rel_l2_mean") or {})
                                                                   .get(c)), optional=True) for c in channels],
                   Column("all channels, physical units", lambda r: sci(r["rec"]["final_mse_mean"]))]
        return [Section("Per channel, approximate initial condition", (
            "Final-time MSE of each scored channel divided by that channel's data variance (so that channels in "
            "different units compare), mean over the test trajectories; the last column is the Eq. 18 MSE in "
            "physical units, as in the tables above.", tabulate(rows, columns)))]

    def bar_charts(self, records: Records) -> list[BarChart]:
        charts = []
        for initial in ("approximate", "exact"):
            crit = {"experiment": "main", "initial": initial}
            panels = (_panel(records, "(a) forward run", crit, filter="forward", **crit),
                      _panel(records, "(b) EKF", crit, filter="ekf", **crit))
            charts.append(BarChart(f"main_{initial}", panels,
                                   f"{records.benchmark}: {initial} initial condition, r=32, 20% noise"))
        return charts

    def figures(self, records: Records, folder: Path, results: dict[tuple, AssimilationResult] | None = None,
                dataset: Dataset | None = None) -> list[Path]:
        cfg, written = records.config, super().figures(records, folder)
        for initial in ("approximate", "exact"):
            crit = {"experiment": "main", "initial": initial}
            rows = [(name, [rec for m in MODELS if (rec := records.find(model=m, filter=f, **crit)) is not None])
                    for f, name in (("forward", "forward run"), ("ekf", "EKF"))]
            time_axis = cfg["t0"] + cfg["dt"] * np.arange(cfg["n_frames"]) if "dt" in cfg else None
            written.append(temporal_error_figure(rows, folder / f"temporal_{initial}.png", time=time_axis,
                                                 title=f"{records.benchmark}: MSE over time, {initial} initial "
                                                       "condition"))
        if results and dataset is not None:
            written += _reconstruction(results, dataset, folder / "reconstruction.png")
        return written


def _reconstruction(results: dict[tuple, AssimilationResult], dataset: Dataset, path: Path) -> list[Path]:
    """Final-time truth / EKF estimate / error per model for the test trajectory with the smallest parameter."""
    found = {m: res for m in MODELS if (res := results.get(Run(m, "ekf").cache_key)) is not None}
    if not found:
        return []
    first = next(iter(found.values()))
    j = int(np.argmin(first.params))
    bench = dataset.benchmark
    # The paper shows the water fraction of the dambreak and a velocity component elsewhere.
    name = "alpha.water" if "alpha.water" in bench.channels else bench.scored_channels[0]
    return [reconstruction_figure(
        {m: res.final_estimate[j] for m, res in found.items()}, first.final_truth[j], dataset.coords, path,
        channel=bench.channels.index(name), channel_name=name, fluid_mask=bench.fluid_mask(dataset.cell_type),
        title=f"{bench.name}: final time, EKF, approximate IC, test trajectory {int(first.trajectories[j])} "
              f"({dataset.param_name}={first.params[j]:.4g})",
    )]


# enkf, calibrated, ensemble ----------------------------------------------------------------------------------
@register
class EnKF(Experiment):
    name = "enkf"
    description = "forward run vs EnKF n=20, four models (Table VII)"

    def runs(self) -> list[Run]:
        return [Run(m, f) for f in ("forward", "enkf") for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        bench = records.benchmark
        rows: list[Row] = [{"model": m, "estimate": "rollout / EnKF", "filter": "enkf",
                            "rollout": records.find(experiment="enkf", model=m, filter="forward"),
                            "filtered": records.find(experiment="enkf", model=m, filter="enkf", n_members=20)}
                           for m in MODELS]
        rows.append({"model": "koopman", "estimate": "EKF (reference)", "filter": "ekf", "reference": True,
                     "filtered": records.find(model="koopman", filter="ekf", **DEFAULT_SCENARIO)})

        def unless_reference(cell: Any) -> Any:
            return lambda r: "" if r.get("reference") else cell(r)

        columns = [MODEL, Column("estimate", lambda r: r["estimate"]),
                   Column("rollout", unless_reference(lambda r: mse(r["rollout"]))),
                   Column("filtered", lambda r: mse(r["filtered"])),
                   Column("rollout rel. L2 (score)", unless_reference(lambda r: rel_l2(r["rollout"])), optional=True),
                   *rel_l2_columns({"filtered": "filtered"}),
                   Column("filtered / rollout", unless_reference(lambda r: mse_ratio(r["filtered"], r["rollout"]))),
                   Column("paper rollout", unless_reference(lambda r: paper_mse(bench, r["model"], "forward"))),
                   Column("paper filtered", lambda r: paper_mse(bench, r["model"], r["filter"]))]
        return [Section("EnKF, n = 20 (Table VII)", (tabulate(rows, columns),))]

    def bar_charts(self, records: Records) -> list[BarChart]:
        crit = {"experiment": "enkf"}
        return [BarChart("enkf", (_panel(records, "(a) forward run", crit, filter="forward", **crit),
                                  _panel(records, "(b) EnKF n=20", crit, filter="enkf", n_members=20, **crit)),
                         f"{records.benchmark}: EnKF, approximate initial condition")]


@register
class Calibrated(Experiment):
    name = "calibrated"
    description = "EKF and EnKF with calibrated Q and P0 (each model's own errors) instead of 1e-4 I and I"

    def runs(self) -> list[Run]:  # the paper-Q runs to compare with are main's and enkf's
        return [Run(m, f, calibrated=True) for f in ("ekf", "enkf") for m in MODELS] + [
            Run(m, "forward") for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        rows = [{"model": m, "forward": records.find(experiment="calibrated", model=m, filter="forward"),
                 "ekf": records.find(experiment="calibrated", model=m, filter="ekf"),
                 "enkf": records.find(experiment="calibrated", model=m, filter="enkf"),
                 "paper ekf": records.find(experiment="main", model=m, filter="ekf", initial="approximate"),
                 "paper enkf": records.find(experiment="enkf", model=m, filter="enkf", n_members=20)}
                for m in MODELS]
        columns = [MODEL, Column("forward run", lambda r: mse(r["forward"])),
                   Column("EKF, paper", lambda r: mse(r["paper ekf"])),
                   Column("EKF, calibrated", lambda r: mse(r["ekf"])),
                   Column("calibrated EKF / forward", lambda r: mse_ratio(r["ekf"], r["forward"])),
                   *rel_l2_columns({"forward": "forward", "ekf": "calibrated EKF", "enkf": "calibrated EnKF"}),
                   Column("EnKF, paper", lambda r: mse(r["paper enkf"])),
                   Column("EnKF, calibrated", lambda r: mse(r["enkf"])),
                   Column("calibrated EnKF / forward", lambda r: mse_ratio(r["enkf"], r["forward"])),
                   Column("95 % coverage, calibrated EKF / EnKF", lambda r: " / ".join(
                       fixed((r[f] or {}).get("final_coverage_mean"), 2) for f in ("ekf", "enkf")))]
        claims = []
        for row in rows:
            if row["forward"] is not None and row["ekf"] is not None:
                gain = row["forward"]["final_mse_mean"] / row["ekf"]["final_mse_mean"]
                claims.append(f"- {label(row)}: calibrated EKF {'no worse than' if gain >= 1 else 'WORSE than'} "
                              f"its forward run (forward / EKF = {sig(gain)})")
        body = ["Paper: Q = 1e-4 I, P0 = I (the runs of the main and EnKF experiments). Calibrated: Q the second "
                "moment of the model's latent one-step residuals on its validation trajectories, P0 the spread of "
                "the encoded first frames around the approximate initial condition plus Q.",
                tabulate(rows, columns), "\n".join(claims)]
        return [Section("Calibrated filter (Q and P0 from each model's own errors)", (*body, *self._scores(records)))]

    @staticmethod
    def _scores(records: Records) -> list[str]:
        """The calibrated filters' predictive-std scores (coverage, NEES, CRPS), when the records hold them."""
        rows = [{"model": m, "filter": f, "rec": rec} for m in MODELS for f in ("ekf", "enkf")
                if (rec := records.find(experiment="calibrated", model=m, filter=f)) is not None
                and rec.get("final_coverage_mean") is not None]
        if not rows:
            return []
        columns = [MODEL, Column("filter", lambda r: "EKF" if r["filter"] == "ekf" else "EnKF"),
                   Column("coverage, final", lambda r: fixed(r["rec"]["final_coverage_mean"], 2)),
                   Column("coverage, all frames", lambda r: fixed(over_steps(r["rec"], "per_step_coverage_mean"), 2)),
                   Column("NEES, all frames", lambda r: sig(over_steps(r["rec"], "per_step_nees_mean"))),
                   Column("NEES, final", lambda r: sig(r["rec"]["final_nees_mean"])),
                   Column("CRPS, final", lambda r: sci(r["rec"]["final_crps_mean"])),
                   Column("spread-skill, final", lambda r: fixed(r["rec"].get("final_spread_skill"), 2), optional=True),
                   Column("spread-skill, all frames", lambda r: fixed(over_steps(r["rec"], "per_step_spread_skill"), 2),
                          optional=True)]
        text = ["Scores of the calibrated filters' predictive std (`estimate_std`): the fraction of scored cells "
                "inside the central 95 % interval (0.95 when calibrated), the mean NEES per cell (1 when "
                "calibrated) and the Gaussian CRPS (physical units), at the final frame and averaged over frames "
                "1 to the last.", tabulate(rows, columns)]
        if any(r["rec"].get("final_spread_skill") is not None for r in rows):
            text.insert(1, "Spread-skill: sqrt(mean std^2 / MSE), both over the scored cells and averaged over the "
                           "test trajectories before dividing (1 when calibrated, below 1 overconfident); "
                           "`figures/spread.png` draws it over time with the EnKF's rank histograms of the truth.")
        return text

    def figures(self, records: Records, folder: Path, results: dict[tuple, AssimilationResult] | None = None,
                dataset: Dataset | None = None) -> list[Path]:
        rows = [(m, {f: records.find(experiment="calibrated", model=m, filter=f) for f in ("ekf", "enkf")})
                for m in MODELS]
        rows = [(m, recs) for m, recs in rows if any((r or {}).get("per_step_spread_skill") for r in recs.values())]
        if not rows:  # records older than the spread diagnostics
            return []
        cfg = records.config
        time_axis = cfg["t0"] + cfg["dt"] * np.arange(cfg["n_frames"]) if "dt" in cfg else None
        return [spread_figure(rows, folder / "spread.png", time=time_axis,
                              title=f"{records.benchmark}: calibrated filters, spread-skill ratio and EnKF rank "
                                    "histograms")]


@register
class Ensemble(Experiment):
    name = "ensemble"
    description = "EnKF with n = 20, 40, 64 members (Table VIII)"
    SIZES = (20, 40, 64)

    def runs(self) -> list[Run]:
        return [Run(m, "forward") for m in NEURAL] + [
            Run(m, "enkf", n_members=n) for n in self.SIZES for m in NEURAL]

    def tables(self, records: Records) -> list[Section]:
        paper = PAPER_ENSEMBLE.get(records.benchmark, PAPER_ENSEMBLE["cylinder"])
        which = "paper" if records.benchmark in PAPER_ENSEMBLE else "paper (cylinder)"
        sizes = {f"n = {n}": n for n in self.SIZES}  # column header: ensemble size
        rows = [{"model": m, **{h: records.find(experiment="ensemble", model=m, filter="enkf", n_members=n)
                                for h, n in sizes.items()}} for m in NEURAL]
        columns = [MODEL, *[Column(h, lambda r, h=h: mse(r[h])) for h in sizes],
                   *rel_l2_columns({h: h for h in sizes}),
                   Column(f"{which} n = 20 / 40 / 64",
                          lambda r: " / ".join(sci(paper[r["model"]][n]) for n in self.SIZES))]
        return [Section("EnKF ensemble size (Table VIII)", (tabulate(rows, columns), *self._collapse(records)))]

    def _collapse(self, records: Records) -> list[str]:
        """The ensemble's spread and gain after a few steps: a collapsed ensemble stops reading the sensors."""
        rows = [{"model": m, "n": n, "spread": rec["per_step_spread_mean"], "gain": rec["per_step_gain_norm_mean"]}
                for m in NEURAL for n in self.SIZES
                if (rec := records.find(experiment="ensemble", model=m, filter="enkf", n_members=n)) is not None
                and rec.get("per_step_spread_mean") and rec.get("per_step_gain_norm_mean")]
        if not rows:
            return []

        def steps(values: list[float]) -> str:
            return " / ".join(sci(values[i]) for i in (0, 4, 9, -1))

        columns = [MODEL, Column("n", lambda r: str(r["n"])),
                   Column("spread, steps 1 / 5 / 10 / last", lambda r: steps(r["spread"])),
                   Column("gain norm, steps 1 / 5 / 10 / last", lambda r: steps(r["gain"]))]
        return ["Does the ensemble collapse? Its spread sqrt(tr P / r) and the gain norm ||K_k||_2 after steps 1, "
                "5, 10 and the last, mean over the test trajectories (a collapsed ensemble has a spread near 0 and "
                "a gain near 0: it stops reading the sensors).", tabulate(rows, columns)]

    def bar_charts(self, records: Records) -> list[BarChart]:
        crit = {"experiment": "ensemble"}
        return [BarChart("ensemble", tuple(_panel(records, f"EnKF n={n}", crit, filter="enkf", n_members=n, **crit)
                                           for n in self.SIZES),
                         f"{records.benchmark}: EnKF ensemble size (÷ MLP forward run)")]


# noise, latent, multistep: one thing of the default scenario varied --------------------------------------------
@register
class Noise(Experiment):
    name = "noise"
    description = "EKF at 10% and 30% measurement noise (Fig. 10)"

    def runs(self) -> list[Run]:
        return [Run(m, f, noise=s) for s in (0.1, 0.3) for f in ("forward", "ekf") for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        def cell(row: Row, s: float) -> str:
            rec = records.find(model=row["model"], filter="ekf", **_scenario(noise=s))
            return f"{mse(rec)} ({mse_ratio(rec, records.base(**_scenario(noise=s)))})"

        def relative(row: Row, s: float) -> str:
            return rel_l2(records.find(model=row["model"], filter="ekf", **_scenario(noise=s)))

        levels = (0.1, 0.2, 0.3)
        columns = [MODEL, *[Column(f"{int(round(100 * s))}%", lambda r, s=s: cell(r, s)) for s in levels],
                   *[Column(f"{int(round(100 * s))}%: rel. L2 (score)", lambda r, s=s: relative(r, s), optional=True)
                     for s in levels]]
        return [Section("Measurement noise (Fig. 10): EKF final MSE (÷ MLP forward run)",
                        (tabulate([{"model": m} for m in MODELS], columns),))]

    def bar_charts(self, records: Records) -> list[BarChart]:
        return [BarChart("noise", tuple(_panel(records, f"EKF, {int(100 * s)}% noise", _scenario(noise=s),
                                               filter="ekf", **_scenario(noise=s)) for s in (0.1, 0.3)),
                         f"{records.benchmark}: measurement noise")]


def _varied_rows(records: Records, name: str, values: tuple, models: tuple[str, ...]) -> list[Row]:
    """Rows (value, model) of a scenario with ``name`` varied, where a forward or EKF record exists."""
    rows = []
    for value in values:
        crit = _scenario(**{name: value})
        for m in models:
            fwd, ekf = (records.find(model=m, filter=f, **crit) for f in ("forward", "ekf"))
            if fwd or ekf:
                rows.append({"model": m, name: value, "forward": fwd, "ekf": ekf, "base": records.base(**crit)})
    return rows


@register
class Latent(Experiment):
    name = "latent"
    description = "EKF at latent dimension r = 16 and 64 (Fig. 11)"

    def runs(self) -> list[Run]:
        return [Run(m, f, r=r) for r in (16, 64) for f in ("forward", "ekf") for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        columns = [Column("r", lambda r: str(r["r"])), MODEL, Column("forward run", lambda r: mse(r["forward"])),
                   Column("EKF", lambda r: mse(r["ekf"])), *rel_l2_columns({"forward": "forward", "ekf": "EKF"}),
                   Column("EKF / MLP fwd (same r)", lambda r: mse_ratio(r["ekf"], r["base"]))]
        return [Section("Latent dimension (Fig. 11)",
                        (tabulate(_varied_rows(records, "r", (16, 32, 64), MODELS), columns),))]

    def bar_charts(self, records: Records) -> list[BarChart]:
        return [BarChart("latent", tuple(_panel(records, f"EKF, r={r}", _scenario(r=r), filter="ekf",
                                                **_scenario(r=r)) for r in (16, 64)),
                         f"{records.benchmark}: latent dimension (each panel ÷ MLP forward run at its r)")]


@register
class Multistep(Experiment):
    name = "multistep"
    description = "Koopman and MLP trained with T = 2, 4, 8 (Fig. 13)"

    def runs(self) -> list[Run]:
        return [Run(m, f, T=t) for t in (2, 4, 8) for f in ("forward", "ekf") for m in ("koopman", "mlp")]

    def tables(self, records: Records) -> list[Section]:
        paper = PAPER_MULTISTEP.get(records.benchmark, PAPER_MULTISTEP["cylinder"])
        which = "paper" if records.benchmark in PAPER_MULTISTEP else "paper (cylinder)"
        columns = [Column("T", lambda r: str(r["T"])), MODEL, Column("forward run", lambda r: mse(r["forward"])),
                   Column("EKF", lambda r: mse(r["ekf"])), *rel_l2_columns({"forward": "forward", "ekf": "EKF"}),
                   Column("EKF / MLP fwd (same T)", lambda r: mse_ratio(r["ekf"], r["base"])),
                   Column(f"{which} forward / EKF", lambda r: " / ".join(
                       sci(paper.get((r["model"], f), {}).get(r["T"])) for f in ("forward", "ekf")))]
        return [Section("Multi-step training (Fig. 13)",
                        (tabulate(_varied_rows(records, "T", (1, 2, 4, 8), ("koopman", "mlp")), columns),))]

    def bar_charts(self, records: Records) -> list[BarChart]:
        panels = tuple(_panel(records, f"T={t}: {name}", _scenario(T=t), filter=f, **_scenario(T=t))
                       for t in (2, 4, 8) for f, name in (("forward", "forward run"), ("ekf", "EKF")))
        return [BarChart("multistep", panels,
                         f"{records.benchmark}: multi-step training (each panel ÷ MLP forward run at its T)", ncols=2)]


# operator norm, timing -----------------------------------------------------------------------------------------
@register
class OperatorNorm(Experiment):
    name = "operator_norm"
    description = "max_k ||F_k||_2 along the EKF and forward runs (Table IX)"

    def runs(self) -> list[Run]:
        return [Run(m, f) for f in ("forward", "ekf") for m in MODELS]

    def present(self, records: Records) -> bool:  # the main experiment's runs carry the same norms
        return bool({"operator_norm", "main"} & records.experiments)

    def tables(self, records: Records) -> list[Section]:
        paper = PAPER_OPERATOR_NORM.get(records.benchmark, {})

        def norm(row: Row, f: str) -> str:
            return fixed(max_norm(records.find(model=row["model"], filter=f, **DEFAULT_SCENARIO)), 4)

        columns = [MODEL, Column("EKF runs", lambda r: norm(r, "ekf")),
                   Column("forward runs", lambda r: norm(r, "forward")),
                   Column("paper", lambda r: sig(paper.get(r["model"]), 4))]
        return [Section("Operator norm max_k ||F_k||_2 over the test runs (Table IX)",
                        (tabulate([{"model": m} for m in MODELS], columns),))]


@register
class Timing(Experiment):
    name = "timing"
    description = "wall time per DA step, one trajectory (B = 1), every model and filter (Figs. 4, 6)"

    def runs(self) -> list[Run]:
        return [Run(m, f, i, single=True) for i in ("approximate", "exact") for f in ("forward", "ekf", "enkf")
                for m in MODELS]

    def tables(self, records: Records) -> list[Section]:
        def ms(rec: Record | None) -> str:
            return MISSING if rec is None or rec["da_step_seconds"] is None else sig(1e3 * rec["da_step_seconds"])

        def batched(row: Row) -> str:
            rec = records.find(experiment="main", model=row["model"], filter="ekf", initial=row["initial"])
            return ms(rec) if rec is None or rec["da_step_seconds"] is None else f"{ms(rec)} (B={rec['batch']})"

        def timed(row: Row, f: str) -> Record | None:
            return records.find(experiment="timing", model=row["model"], filter=f, initial=row["initial"])

        filters = (("forward", "forward"), ("ekf", "EKF"), ("enkf", "EnKF n=20"))
        columns = [Column("initial", lambda r: r["initial"]), MODEL,
                   *[Column(name, lambda r, f=f: ms(timed(r, f))) for f, name in filters],
                   Column("EKF, whole test split batched", batched),
                   *[Column(f"{name} rel. L2 (score)", lambda r, f=f: rel_l2(timed(r, f)), optional=True)
                     for f, name in filters]]  # the final error of the timed trajectory: the accuracy timed
        rows = [{"initial": i, "model": m} for i in ("approximate", "exact") for m in MODELS]
        return [Section(f"Wall time per DA step in ms (Figs. 4, 6), one trajectory, {records.config.get('device')}",
                        (tabulate(rows, columns),))]

    def figures(self, records: Records, folder: Path, results: dict[tuple, AssimilationResult] | None = None,
                dataset: Dataset | None = None) -> list[Path]:
        written = []
        for initial in ("approximate", "exact"):
            recs = records.select(experiment="timing", initial=initial)
            if recs:
                written.append(timing_figure(recs, folder / f"timing_{initial}.png",
                                             title=f"{records.benchmark}: wall time per DA step, {initial} IC, "
                                                   f"{records.config.get('device')}"))
        return written


__all__ = ["MODELS"]
