"""One declaration per loss term (threestudio-style ``lambda_<name>``).

Each stage lists its terms in a table of :class:`LossTerm`: the name (logged as
``train/loss_<name>``), the function that computes it, and where its weight lives:
``lambda_<name>`` of the stage's config section (``reconstruct.lambda_rgb``,
``experiment.lambda_dir``, ...). A term whose weight is 0, or that does not apply
to the run (no masks, frozen geometry, no local patches), is not computed.

The field's regularizers (``Field.regularizers``: ``eikonal`` for SDF fields,
``grid_tv`` for ``encoding.tv_weight > 0``, ...) join the table generically
(instant-nsr-pl style): each is weighted by the section's ``lambda_<name>`` when
the section declares one (``lambda_eikonal``), else by 1, because its component
already weighs it (``encoding.tv_weight``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

from pydantic import BaseModel
from torch import Tensor

from nerfart_plugin.systems.callbacks import check_finite_losses


@dataclass(frozen=True)
class LossTerm:
    """One term of a stage's loss.

    Attributes:
        name: logged as ``train/loss_<name>``; its weight is ``lambda_<name>`` of the stage's section.
        fn: computes the (0-dim) term; its arguments are the stage's (see the tables).
        geometry: the term only shapes geometry (off when ``stylize.freeze_geometry``).
        doc: the equation / meaning, for the tables' readers.
    """

    name: str
    fn: Callable[..., Tensor]
    geometry: bool = False
    doc: str = ""

    @property
    def lambda_key(self) -> str:
        return f"lambda_{self.name}"


def weights_of(terms: Iterable[LossTerm], cfg: BaseModel, off: Iterable[str] = ()) -> dict[str, float]:
    """``name -> lambda_<name>`` of ``cfg`` for each term, 0 for those named in ``off`` (not applicable)."""
    off = set(off)
    return {t.name: 0.0 if t.name in off else float(getattr(cfg, t.lambda_key)) for t in terms}


def regularizer_weights(names: Iterable[str], cfg: BaseModel, off: bool = False) -> dict[str, float]:
    """The field's regularizers ``names`` weighted by ``cfg.lambda_<name>`` where the section declares it,
    else 1 (the component weighs the term itself); all 0 with ``off``."""
    fields = type(cfg).model_fields
    return {n: 0.0 if off else float(getattr(cfg, f"lambda_{n}")) if f"lambda_{n}" in fields else 1.0
            for n in names}


def compute(terms: Iterable[LossTerm], weights: Mapping[str, float], *args: Any) -> dict[str, Tensor]:
    """The terms with a non-zero weight, each ``term.fn(*args)``."""
    return {t.name: t.fn(*args) for t in terms if weights[t.name] != 0.0}


def regularizer_terms(out: Mapping[str, Any], weights: Mapping[str, float]) -> dict[str, Tensor]:
    """The field regularizers of a render ``out`` (``out["regularizers"]``) with a non-zero weight."""
    return {k: v for k, v in out["regularizers"].items() if weights[k] != 0.0}


def weighted_sum(terms: Mapping[str, Tensor], weights: Mapping[str, float], step: int, stage: str) -> Tensor | float:
    """``sum_k lambda_k L_k`` (0 without terms) after checking every term is finite (TrainingDivergedError
    names the bad ones)."""
    check_finite_losses(dict(terms), step, stage)
    return sum((weights[k] * v for k, v in terms.items()), 0.0)
