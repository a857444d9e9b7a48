"""An experiment of ``dks-gym reproduce`` as one object: the runs it needs, its tables and its figures.

An :class:`Experiment` subclass is the whole definition of an experiment; :func:`register` puts an instance
in :data:`EXPERIMENTS`, the one registry that ``reproduce``, its ``--only`` choices, the tables and the
figures read. The tables are built with :func:`~dks_gym.evaluation.tabulate.tabulate`; the order of the
registry is the order of the runs and of the tables' sections.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from ..assimilation import AssimilationResult
from ..dataset import Dataset
from .figures import normalized_bar_chart
from .tabulate import Records


@dataclass(frozen=True)
class Run:
    """One batched assimilation run: a model (kind, r, T) under one filter configuration."""

    model: str
    filter: str
    initial: str = "approximate"
    noise: float = 0.2
    r: int = 32
    T: int = 1
    n_members: int = 20
    single: bool = False  # one trajectory (B = 1) instead of the whole test split: the timing experiment
    calibrated: bool = False  # Q and P0 measured on the model's own errors instead of the paper's 1e-4 I and I
    parameter: str = "known"  # the filter told mu, estimating it ("estimate") or assuming the prior's mean

    @property
    def model_key(self) -> tuple[str, int, int]:
        """The trained model the run needs: (kind, r, T); pDMD has no training horizon."""
        return (self.model, self.r, 1 if self.model == "pdmd" else self.T)

    @property
    def cache_key(self) -> tuple:
        """What makes two runs the same computation (experiments repeat identical runs: computed once)."""
        n = self.n_members if self.filter == "enkf" else None
        return (self.model, self.filter, self.initial, self.noise, self.r, self.T, n, self.single, self.calibrated,
                self.parameter)

    def record_key(self, experiment: str) -> tuple:
        """The results-file identity (:func:`~dks_gym.evaluation.results.record_key`) of the run in ``experiment``."""
        n = self.n_members if self.filter == "enkf" else None
        return (experiment, self.model, self.filter, self.initial, self.noise, self.r, self.T, n, self.parameter)


@dataclass(frozen=True)
class Section:
    """One section of the tables: a ``## title``, then paragraphs and tables (markdown), in order."""

    title: str
    body: tuple[str, ...]

    def markdown(self) -> str:
        """The section as markdown, each part a paragraph of its own."""
        return "\n\n".join((f"## {self.title}", *self.body))


@dataclass(frozen=True)
class BarChart:
    """A figure of the paper's normalized bars (each model's error over the MLP forward run's): the file's
    name without ``.png``, the panels (title, records, the normalizing record; None for a panel without
    data), the title and the number of panel columns."""

    name: str
    panels: tuple[tuple | None, ...]
    title: str
    ncols: int | None = None


class Experiment:
    """An experiment of the paper's Section IV: override :meth:`runs`, :meth:`tables` and :meth:`figures`.

    ``name`` is what ``--only`` takes and what the records' ``experiment`` field holds; ``description``
    is the one line ``dks-gym reproduce --help`` shows.
    """

    name: str = ""
    description: str = ""

    def runs(self) -> list[Run]:
        """The runs the experiment needs, in the order they run."""
        raise NotImplementedError

    def present(self, records: Records) -> bool:
        """Whether ``records`` hold this experiment (its tables and figures are drawn only then)."""
        return self.name in records.experiments

    def tables(self, records: Records) -> list[Section]:
        """The experiment's sections of tables.md."""
        return []

    def bar_charts(self, records: Records) -> list[BarChart]:
        """The experiment's bar charts (drawn by :meth:`figures`)."""
        return []

    def figures(self, records: Records, folder: Path, results: dict[tuple, AssimilationResult] | None = None,
                dataset: Dataset | None = None) -> list[Path]:
        """Draw the experiment's figures into ``folder``: its :meth:`bar_charts` that have data; override to
        draw more. ``results`` (by :attr:`Run.cache_key`) and ``dataset`` are the run's own, when it just
        ran (fields are not in the records)."""
        written = []
        for chart in self.bar_charts(records):
            panels = [p for p in chart.panels if p is not None]
            if panels:
                written.append(normalized_bar_chart(panels, folder / f"{chart.name}.png", title=chart.title,
                                                    ncols=chart.ncols))
        return written


#: The experiments of ``dks-gym reproduce`` by name, in the order they run and print.
EXPERIMENTS: dict[str, Experiment] = {}

E = TypeVar("E", bound=type[Experiment])


def register(cls: E) -> E:
    """Class decorator: add an instance of the experiment ``cls`` to :data:`EXPERIMENTS`."""
    if not cls.name or cls.name in EXPERIMENTS:
        raise ValueError(f"an experiment needs a new, non-empty name; got {cls.name!r} "
                         f"(registered: {', '.join(EXPERIMENTS)})")
    EXPERIMENTS[cls.name] = cls()
    return cls


__all__ = ["EXPERIMENTS", "BarChart", "Experiment", "Run", "Section", "register"]
