"""What the diagnosis searches over: the model so far as a chain of fitted stages (the GPI, then each added
effect in the order found), and the validation record it is judged on."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.effects import EffectFit, check_record
from sma_stage.identify.fit import FitResult, information_criterion
from sma_stage.identify.metrics import ErrorMetrics, error_metrics, worst
from sma_stage.identify.residual_tests import ResidualTests, residual_tests
from sma_stage.identify.start import StartFit, estimate_start, start_fit
from sma_stage.model.identified import IdentifiedModel, Start

Record = tuple[np.ndarray, np.ndarray, np.ndarray]


Record = tuple[np.ndarray, np.ndarray, np.ndarray]


def as_record(data: object, name: str) -> Record:
    """(t, u, y) from a Series-like object (attributes t, input, output) or a (t, u, y) triple."""
    if all(hasattr(data, attribute) for attribute in ("t", "input", "output")):
        t, u, y = data.t, data.input, data.output
    else:
        try:
            t, u, y = data
        except (TypeError, ValueError):
            raise InputError(f"{name} data must be a Series or a (t, u, y) triple") from None
    try:
        return check_record(t, u, y)
    except InputError as error:
        raise InputError(f"{name} data: {error}") from None


@dataclass(frozen=True)
class Chain:
    """The model so far: the plain GPI fit, then each added effect in the order found. Each stage was
    fitted on the input and output the stages before it make (their input transforms applied in turn,
    their output offsets taken off); the last one predicts."""

    stages: tuple[EffectFit, ...]
    base: FitResult = field(repr=False, compare=False)

    @property
    def effects(self) -> list[str]:
        """Names of the added effects, in order."""
        return [stage.effect for stage in self.stages[1:]]

    @property
    def parameters(self) -> dict[str, float]:
        """Every added effect's parameters."""
        return {name: value for stage in self.stages[1:] for name, value in stage.parameters.items()}

    @property
    def last(self) -> EffectFit:
        return self.stages[-1]

    @property
    def composable(self) -> bool:
        """Whether a further effect can be fitted on top (see the module docstring)."""
        return self.last.composable

    @property
    def bic(self) -> float:
        """BIC on the identification data, counting the parameters of every stage."""
        earlier = sum(len(stage.parameters) for stage in self.stages[:-1])
        return information_criterion(self.last.cost, self.last.samples, self.last.parameter_count + earlier)

    @property
    def model(self) -> IdentifiedModel:
        """The whole model: the last stage's GPI with every added effect, in the order found."""
        last = self.last
        effects = tuple(stage.spec for stage in self.stages[1:])
        return IdentifiedModel(last.gpi_parameters, last.operators, effects)

    @property
    def start(self) -> str:
        """How the identification record starts for this model: the first added effect's start (rest or
        held; later effects are fitted from the same)."""
        return self.stages[1].start if len(self.stages) > 1 else "rest"

    def data(self, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(input, output) as an effect added on top sees them: every stage's input transform applied in
        turn (from the chain's start), every output offset taken off."""
        v, offset = u, np.zeros_like(t)
        for stage in self.stages[1:]:
            spec = stage.spec
            if spec.role == "input":
                v = spec.transform(t, v, spec.start_state(t, v, self.start))[0]
            elif spec.role == "output":
                offset = offset + spec.offset(t)[0]
        return v, y - offset

    def predict(self, t: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Output [output unit] of the whole model for the identification record (t [s], u [A]) from its start."""
        return self.model.predict_from(t, u, Start(self.start))

    def then(self, stage: EffectFit) -> Chain:
        """This model with one more effect."""
        return Chain((*self.stages, stage), self.base)

    def without(self, index: int) -> Chain:
        """This model without stage `index` (an added effect; the last stage keeps its GPI)."""
        return Chain(self.stages[:index] + self.stages[index + 1:], self.base)

    @property
    def refittable(self) -> bool:
        """Whether every added effect can be fitted again on top of the others: they are input
        transforms that commute (linear, time-invariant: lag, delay) and output offsets, so their order
        does not matter."""
        return all(stage.composable for stage in self.stages)


@dataclass(frozen=True)
class Validation:
    """The validation record (t [s], u [A], y) and the sample its errors count from. A separate record
    (scored_from 0) starts as estimate_start finds for each model; a record that continues the
    identification record (its errors counted from scored_from) runs from the identification's start."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    scored_from: int = 0
    others: tuple[Record, ...] = ()  # further validation records (t, u, y), each run from rest

    def predict(self, model: IdentifiedModel, identification_start: str) -> StartFit:
        """The model's output over the record, and the start it runs from."""
        if self.scored_from > 0:
            return start_fit(model, self.t, self.u, self.y, Start(identification_start))
        return estimate_start(model, self.t, self.u, self.y)

    def errors(self, predicted: np.ndarray) -> ErrorMetrics:
        """RMS and max error of a prediction over the scored samples [% of their span]."""
        return error_metrics(self.y[self.scored_from:], predicted[self.scored_from:])

    def worst_errors(self, model: IdentifiedModel, identification_start: str) -> ErrorMetrics:
        """The model's errors on the record it predicts worst (largest RMS % of the record's span): this one, or
        one of `others`, each run from rest (as the families are scored on them)."""
        errors = [self.errors(self.predict(model, identification_start).predicted)]
        errors += [error_metrics(y, model.without_state().predict(t, u)) for t, u, y in self.others]
        return worst(errors)

    def tests(self, predicted: np.ndarray) -> ResidualTests:
        """The residual tests of a prediction over the scored samples."""
        k = self.scored_from
        return residual_tests((self.y - predicted)[k:], self.u[k:], self.t[k:])
