"""Model families compared on the same identification record: the GPI (with the effects its diagnosis added),
the same GPI with free density weights, the two-wire model, and the Bouc-Wen model as a baseline from outside
the Prandtl-Ishlinskii family (FAMILIES, the default); when named, the two-wire model with a compact transformation
onset (`two_wire_compact`: a wire does not move the stage below its transformation start). The choice: the lowest
held-out RMS error (with several validation records, on the record each family predicts worst), and among the
families within PARSIMONY of it, the lowest BIC on the identification record (the simpler explanation when the
held-out data cannot tell).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.bouc_wen import BoucWenFit, fit_bouc_wen
from sma_stage.identify.fit import information_criterion
from sma_stage.identify.free_weights import fit_free_weights
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.identify.metrics import worst as worst_record
from sma_stage.identify.two_wire import HeldOut, TwoWireFit, TwoWireFitting
from sma_stage.identify.workers import Pending, Workers
from sma_stage.io.series import Series
from sma_stage.model.identified import IdentifiedModel, Start

FAMILIES = ("gpi", "gpi_free", "two_wire", "bouc_wen")  # fitted unless the families are named
KNOWN_FAMILIES = ("gpi", "gpi_free", "two_wire", "two_wire_compact", "bouc_wen")
HELD_CURRENT_FAMILIES = ("two_wire", "two_wire_compact", "bouc_wen")  # fitted apart from the GPI's diagnosis, in its
# workers' processes
ONSET = {"two_wire": "tanh", "two_wire_compact": "compact"}  # the two-wire families' transformation curves
PARSIMONY = 0.05  # families within 5 % (relative) of the best held-out RMS are told apart by BIC


@dataclass(frozen=True)
class FamilyRow:
    """One family's outcome: what was fitted, its free parameters, its errors (None: not scored), its BIC on
    the identification record, and why it was not fitted (empty when it was)."""

    family: str
    description: str
    parameters: int = 0
    identification: ErrorMetrics | None = None
    validation: ErrorMetrics | None = None
    bic: float = float("nan")
    not_fitted: str = ""
    chosen: bool = False
    more_validation: tuple[ErrorMetrics | None, ...] = ()  # on the further validation records, in their order

    @property
    def worst(self) -> ErrorMetrics | None:
        """The errors on the validation record it predicts worst (by RMS): what the choice goes by (None: not
        scored on every record)."""
        every = (self.validation, *self.more_validation)
        return None if any(errors is None for errors in every) else worst_record(every)

    def to_dict(self) -> dict[str, object]:
        """The report's form (with more than one validation record: every record's errors, and the worst)."""
        found = {"family": self.family, "model": self.description, "parameters": self.parameters,
                 "identification": None if self.identification is None else self.identification.to_dict(),
                 "validation": None if self.validation is None else self.validation.to_dict(),
                 "bic": self.bic, "chosen": self.chosen, "not_fitted": self.not_fitted}
        if self.more_validation:
            found["more_validation"] = [None if errors is None else errors.to_dict() for errors in self.more_validation]
            found["worst_validation"] = None if self.worst is None else self.worst.to_dict()
        return found


def check_families(names: Sequence[str]) -> tuple[str, ...]:
    """The families named, in KNOWN_FAMILIES order; InputError for an unknown name or none."""
    names = [name.strip() for name in names if name.strip()]
    unknown = [name for name in names if name not in KNOWN_FAMILIES]
    if unknown or not names:
        problem = f"unknown model family {unknown[0]!r}" if unknown else "no model family given"
        raise InputError(f"{problem} (known: {', '.join(KNOWN_FAMILIES)})")
    return tuple(name for name in KNOWN_FAMILIES if name in names)


def start_held_current_fit(family: str, ident: Series, output_unit: str, pool: Workers,
                           held_out: HeldOut | None = None) -> Pending:
    """A held-current family's fit (HELD_CURRENT_FAMILIES) on the identification record, begun in the pool's
    processes; its result is the fit, or raises the InputError that says why the record cannot identify it (its
    `begin()` hands the two-wire fit's last jobs, the polish, to the pool once its starts are done).
    held_out: the validation record the two-wire fit tells its closest starts apart on and judges its tension
    coupling on (fit_two_wire)."""
    if family == "bouc_wen":
        return pool.submit(fit_bouc_wen, ident.t, ident.input, ident.output, output_unit)
    try:
        fitting = TwoWireFitting(ident.t, ident.input, ident.output, output_unit=output_unit, pool=pool,
                                 held_out=held_out, onset=ONSET[family])
    except InputError as error:
        return Pending(partial(_raise, error))
    return Pending(fitting.result, begin=fitting.polish)


def _raise(error: Exception) -> None:
    raise error


def held_current_row(family: str, fitting: Pending, record: Series | None, scored_from: int
                     ) -> tuple[FamilyRow, TwoWireFit | BoucWenFit | None]:
    """A held-current family's row: its fit (start_held_current_fit) scored on the validation record (`record`,
    from its sample scored_from: a separate record run from rest, or the whole record whose tail is held out)."""
    try:
        found = fitting.result()
    except InputError as error:
        return FamilyRow(family, family.replace("_", "-"), not_fitted=str(error)), None
    validation = None
    if record is not None and np.ptp(record.output[scored_from:]) > 0.0:
        predicted = found.model.without_state().predict(record.t, record.input)
        validation = error_metrics(record.output[scored_from:], predicted[scored_from:])
    if family in ONSET:
        params = found.model.parameters
        onset = "compact onset, " if ONSET[family] == "compact" else ""
        description = (f"two-wire, {onset}{params.wire_operators} operators per wire, {params.output_operators} output "
                       "operators" + (f", the start of {found.admitted} that predicts best" if found.admitted > 1 else "")
                       + (f"; {found.tension}" if found.tension else ""))
    else:
        description = f"Bouc-Wen through a heating lag of {found.model.tau_s:.3g} s"
    return FamilyRow(family, description, found.parameter_count, found.errors, validation, found.bic), found


def fit_free_weights_row(gpi: IdentifiedModel, gpi_parameters: int, ident: Series, ident_start: Start,
                         record: Series | None, scored_from: int, record_start: Start
                         ) -> tuple[FamilyRow, IdentifiedModel | None]:
    """The GPI family's model (gpi_parameters free parameters) with free density weights fitted on the
    identification record, scored on the validation record as the GPI is (each record from the start found for
    it)."""
    try:
        model = fit_free_weights(gpi, ident.t, ident.input, ident.output, ident_start)
    except InputError as error:
        return FamilyRow("gpi_free", "GPI, free weights", not_fitted=str(error)), None
    fitted = model.predict_from(ident.t, ident.input, ident_start)
    identification = error_metrics(ident.output, fitted)
    count = gpi_parameters - 2 + model.operators  # a10, a11 out, one weight per operator in
    bic = information_criterion(float(np.sum((ident.output - fitted) ** 2)), len(ident), count)
    validation = None
    if record is not None and np.ptp(record.output[scored_from:]) > 0.0:
        predicted = model.predict_from(record.t, record.input, record_start)
        validation = error_metrics(record.output[scored_from:], predicted[scored_from:])
    effects = " + ".join(model.effect_names) or "no effect"
    description = f"GPI, {model.operators} operators, free weights, {effects}"
    return FamilyRow("gpi_free", description, count, identification, validation, bic), model


def choose(rows: Sequence[FamilyRow]) -> int | None:
    """The index of the chosen row among those fitted and scored (None when none is), by the errors on the
    validation record each predicts worst."""
    scored = [index for index, row in enumerate(rows) if row.worst is not None and not row.not_fitted]
    if not scored:
        return None
    best = min(rows[index].worst.rms_pct for index in scored)
    close = [index for index in scored if rows[index].worst.rms_pct <= best * (1.0 + PARSIMONY)]
    return min(close, key=lambda index: rows[index].bic)
