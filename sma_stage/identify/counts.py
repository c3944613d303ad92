"""The operator count of a diagnosed model, chosen by the identification BIC and the held-out error
together (`count_by_held_out`), the counts fitted in the worker pool."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sma_stage.identify.cancel import Progress, report
from sma_stage.identify.chain import Chain, Record, Validation
from sma_stage.identify.effects import NotFitted, attempt, lowest_cost
from sma_stage.identify.fit import OPERATOR_CANDIDATES, SCREEN_SAMPLES, FitResult, fit_gpi, thinned
from sma_stage.identify.metrics import error_metrics
from sma_stage.identify.workers import Pending, Workers
from sma_stage.model.forward import forward
from sma_stage.model.parameters import GPIParameters

COUNT_FIT_MARGIN = 0.10  # operator counts whose identification RMS is within 10 % of the best are admitted
COUNT_TIE = 0.01  # validation RMS within 1 % of the lowest: the smaller operator count is kept


COUNT_FIT_MARGIN = 0.10  # operator counts whose identification RMS is within 10 % of the best are admitted


COUNT_TIE = 0.01  # validation RMS within 1 % of the lowest: the smaller operator count is kept


def count_by_held_out(chain: Chain, ident: Record, valid: Validation, progress: Progress = None,
                      cold: bool = True, pool: Workers | None = None, begun: ColdFit | None = None
                      ) -> tuple[Chain, dict[str, object]]:
    """The operator count of the model chosen by the identification BIC and the held-out error together:
    the GPI refitted at every count of OPERATOR_CANDIDATES with the effects held (from the model's GPI and,
    when cold, from a cold fit of every count, the better kept; on a copy thinned to SCREEN_SAMPLES, the chosen count
    then refitted on all samples). Every count has the same parameters, so the BIC only ranks their fit
    to the identification data, where more operators fit a little closer; the held-out error says which
    of them generalises. The BIC admits the counts whose RMS error there is within COUNT_FIT_MARGIN of
    the best (a BIC within 2 N ln(1 + COUNT_FIT_MARGIN): a fit that failed is not chosen for luck on the
    validation record), and of those the lowest validation RMS wins, the smaller count on a near-tie
    (COUNT_TIE). The counts are fitted in the pool's processes when one is given; `begun`, a cold fit begun
    earlier (begin_cold_fit), is taken when it was begun on the same data. Returns the
    chain with that count and the report's "operators" block (the choice, the runner-up, every count's
    BIC and validation RMS)."""
    t_i, u_i, y_i = ident
    v_i, w_i = chain.data(t_i, u_i, y_i)
    last, unit = chain.last, chain.last.gpi_parameters.output_unit
    keep = thinned(v_i, SCREEN_SAMPLES)
    cold_fit = None
    if cold:
        ready = begun is not None and begun.fits(v_i, w_i)
        cold_fit = begun.pending.result() if ready else _cold_fit(v_i, w_i, unit)
    cold_fits = cold_fit.by_count if isinstance(cold_fit, FitResult) else {}
    jobs = [(count, chain, (v_i, w_i, y_i), valid, cold_fits.get(count)) for count in OPERATOR_CANDIDATES
            if count != last.operators]
    pool = pool or Workers()
    options: dict[int, Chain] = {last.operators: chain}
    rows = {last.operators: _count_row(chain, valid)}
    for (count, *_), outcome in zip(jobs, pool.run(_count_option, jobs, progress, "fitting {}", name=_count_name, cost=_count_cost), strict=True):
        if isinstance(outcome, str):
            report(progress, f"{count} operators: {outcome}")
            continue
        options[count], rows[count] = outcome
    best_bic = min(row["bic"] for row in rows.values())
    margin = 2.0 * y_i.size * math.log1p(COUNT_FIT_MARGIN)
    admissible = sorted((count for count, row in rows.items() if row["bic"] <= best_bic + margin),
                        key=lambda count: (rows[count]["validation_rms_pct"], count))
    lowest = rows[admissible[0]]["validation_rms_pct"]
    chosen = min(count for count in admissible if rows[count]["validation_rms_pct"] <= (1.0 + COUNT_TIE) * lowest)
    runner_up = next((count for count in admissible if count != chosen), None)
    found_chain = options[chosen]
    if chosen != last.operators and keep.size < v_i.size:
        polished = attempt("GPI", lambda: fit_gpi(v_i, w_i, operators=chosen, initial=found_chain.last.gpi_parameters,
                                                  output_unit=unit))
        if not isinstance(polished, NotFitted):
            found_chain = _with_gpi(chain, polished.parameters, chosen, v_i, w_i, y_i)
    report(progress, f"operators: {chosen} chosen (runner-up {runner_up}) by BIC and held-out error")
    return found_chain, {"chosen": chosen, "runner_up": runner_up,
                         "by_count": {str(count): rows[count] for count in sorted(rows)}}


@dataclass(frozen=True)
class ColdFit:
    """A cold fit of every operator count (count_by_held_out's) under way on what a chain leaves of the
    identification record (v, w)."""

    v: np.ndarray
    w: np.ndarray
    pending: Pending

    def fits(self, v: np.ndarray, w: np.ndarray) -> bool:
        """Whether it was begun on these data."""
        return np.array_equal(self.v, v) and np.array_equal(self.w, w)


def begin_cold_fit(v: np.ndarray, w: np.ndarray, unit: str, pool: Workers) -> ColdFit:
    """count_by_held_out's cold fit of (v, w) begun in the pool's processes (with workers 1: when asked for)."""
    return ColdFit(v, w, pool.submit(_cold_fit, v, w, unit))


def _cold_fit(v: np.ndarray, w: np.ndarray, unit: str) -> FitResult | NotFitted:
    """A fit of every operator count from cold starts on (v, w) thinned to SCREEN_SAMPLES."""
    keep = thinned(v, SCREEN_SAMPLES)
    return attempt("GPI", lambda: fit_gpi(v[keep], w[keep], output_unit=unit))


def _count_option(count: int, chain: Chain, data: tuple[np.ndarray, np.ndarray, np.ndarray], valid: Validation,
                  cold_start: GPIParameters | None, progress: Progress = None) -> tuple[Chain, dict[str, float]] | str:
    """The chain with its GPI refitted at `count` operators (effects held; from the chain's GPI carried to
    the count and from cold_start, the better kept, on the SCREEN_SAMPLES copy) and its report row (BIC,
    validation RMS); why not, when no fit was found. data: (v_i, w_i, y_i), what the chain's effects
    leave of the identification record (chain.data) and its output."""
    v_i, w_i, y_i = data
    last, unit = chain.last, chain.last.gpi_parameters.output_unit
    keep = thinned(v_i, SCREEN_SAMPLES)
    carried = last.gpi_parameters.replace(a9=last.gpi_parameters.a9 * max(last.operators - 1, 1) / max(count - 1, 1))
    tries = [attempt("GPI", lambda initial=initial: fit_gpi(v_i[keep], w_i[keep], operators=count, initial=initial,
                                                            output_unit=unit))
             for initial in (carried, cold_start) if initial is not None]
    found = lowest_cost(fit for fit in tries if not isinstance(fit, NotFitted))
    if found is None:
        return "; ".join(str(fit) for fit in tries)
    option = _with_gpi(chain, found.parameters, count, v_i, w_i, y_i)
    return option, _count_row(option, valid)


def _count_row(option: Chain, valid: Validation) -> dict[str, float]:
    return {"bic": option.bic, "validation_rms_pct": valid.errors(valid.predict(option.model, option.start).predicted).rms_pct}


def _with_gpi(chain: Chain, parameters: GPIParameters, operators: int, v_i: np.ndarray, w_i: np.ndarray,
              y_i: np.ndarray) -> Chain:
    """The chain with its last GPI replaced (the effects held), scored on the whole identification record."""
    predicted = forward(v_i, parameters, operators) + (y_i - w_i)
    residual = y_i - predicted
    stage = replace(chain.last, gpi_parameters=parameters, operators=operators, cost=float(residual @ residual),
                    identification=error_metrics(y_i, predicted))
    return chain.without(len(chain.stages) - 1).then(stage)


def _count_name(job: tuple) -> str:
    return f"{job[0]} operators"


def _count_cost(job: tuple) -> float:
    """About how long fitting a count takes, to hand out the costliest first: the count."""
    return float(job[0])
