"""One resolver from what a user hands a wrapper as its model to the model object the filter runs.

:func:`resolve_model` takes a kind name ("koopman": the default lookup), a :class:`~dks_gym.models.ModelSpec`
(any other lookup: r, preset, T, device, ``train_if_missing``) or a model object
(a :class:`~dks_gym.models.FilterableModel`), and checks the result against the environment's benchmark.
Nothing is trained or written unless a spec says ``train_if_missing=True``.
"""

from __future__ import annotations

from ..dataset import Dataset
from ..models import MODEL_KINDS, FilterableModel, ModelSpec, missing_members
from .tuning import tune_if_missing

#: What a wrapper accepts as its model.
ModelLike = str | ModelSpec | FilterableModel


def resolve_model(model: ModelLike, benchmark: str, dataset: Dataset | None = None) -> FilterableModel:
    """The model object ``model`` stands for, checked to be a model of ``benchmark``.

    A name is ``ModelSpec(name)``; a spec is looked up by :meth:`ModelSpec.load` (the user's checkpoint,
    then the shipped one) for ``dataset``, the environment's data, and a model a spec trained
    (``train_if_missing=True``) also gets its Q scale tuned on it. A model object is used as it is.
    """
    if isinstance(model, str):
        model = ModelSpec(model)
    if isinstance(model, ModelSpec):
        spec, model = model, model.load(benchmark, dataset)
        if spec.train_if_missing and dataset is not None:  # asked to prepare a missing model: tune it too
            tune_if_missing(model, dataset)
    missing = missing_members(model)
    if missing:
        raise TypeError(f"model must be one of {', '.join(MODEL_KINDS)}, a dks_gym.models.ModelSpec or a model "
                        f"object (dks_gym.models.FilterableModel); {type(model).__name__} lacks "
                        f"{', '.join(map(repr, missing))}")
    if model.benchmark != benchmark:
        raise ValueError(f"the model was trained for {model.benchmark!r}, but the environment is {benchmark!r}")
    return model
