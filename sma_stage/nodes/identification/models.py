"""The models in force: the history of every model the compensator took, `~/rollback`, and what the model watch
does on drift (report, refit, excite). Mixed into IdentificationNode."""

from __future__ import annotations

import json
from collections.abc import Callable

from std_msgs.msg import String
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Cancelled
from sma_stage.identify.history import judge_swap, started_from
from sma_stage.identify.pipeline import (
    dynamics_held_refusal,
    refit_hysteresis,
)
from sma_stage.identify.watch import ModelWatch
from sma_stage.io import make_series
from sma_stage.io.series import Series
from sma_stage.model.kinds import any_model_from_yaml_text
from sma_stage.nodes.identification.refit import report_json, report_path


class ModelsRoom:
    """The history, ~/rollback, and the watch's ticks and drift (uses the node's settings, lock and refit)."""

    def publish_report(self, report: dict | None = None) -> None:
        """Publish the last refit's report (or this new one) on ~/report with the history of the models in force."""
        if report is not None:
            self.last_report = report
        document = {**(self.last_report or {}), "history": self.history.to_report()}
        self.report_pub.publish(String(data=report_json(document)))

    def on_model_in_force(self, message: String) -> None:
        """The compensator's model in force: noted in the history (one log line when it is another one) and
        watched."""
        try:
            document = json.loads(message.data)
            model = any_model_from_yaml_text(str(document["model"]))
        except (InputError, ValueError, KeyError, TypeError) as error:
            self.get_logger().warning(f"the compensator's model cannot be read: {' '.join(str(error).split())}")
            return
        source = str(document.get("source", "unknown"))
        reason, self._push_reason = self._push_reason or "set on the compensator", None
        held_out = (model.metadata or {}).get("held_out_rms")
        span = (model.metadata or {}).get("output_span")
        held_out_pct = 100.0 * float(held_out) / float(span) if held_out and span else None
        entry = self.history.note(model, source, reason, self.now_ns() * 1e-9, held_out_pct)
        if entry is not None:
            self.get_logger().info(f"model in force: {source} ({reason}); {len(self.history.entries)} in the history")
            self._drift_refit_from_s = None
            self.publish_report()
        if self.watch is not None:
            self.watch.set_model(model, source)

    def on_rollback(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Push the model in force before the one now, started where the recent record leaves it."""
        previous = self.history.previous
        if previous is None:
            response.success, response.message = False, "no model before the one in force to roll back to"
            return response
        source, since_s = previous.source, previous.since_s  # the entry is noted again once the model is in force
        t_s, current_a, _ = self.watch.recent_arrays() if self.watch is not None else ((), (), ())
        pushed = self.push(started_from(previous.model, t_s, current_a), f"~/rollback to the model from {source}")
        response.success = pushed["pushed"]
        response.message = (f"rolled back to the model from {source} (in force from {since_s:.1f} s until the one "
                            "rolled back)" if pushed["pushed"] else f"rollback failed: {pushed['message']}")
        log = self.get_logger().info if pushed["pushed"] else self.get_logger().warning
        log(f"~/rollback: {response.message}")
        return response

    def on_watch_tick(self) -> None:
        """Run the watch; start a refit on drift once the record from the change's onset is long enough."""
        self.watch.run()
        start_s = self._drift_refit_from_s
        if start_s is None:
            return
        t_s, _, _ = self.watch.recent_arrays()
        if len(t_s) and t_s[-1] - start_s >= self.settings.drift_refit_record:
            self._drift_refit_from_s = None
            self.start_guarded_refit(f"the record from {start_s:.0f} s, where the change began",
                                     lambda: self.recent_series(start_s),
                                     hysteresis_only=self.settings.drift_refit_scope == "hysteresis")

    def on_drift(self, watch: ModelWatch) -> None:
        """The watch turned to drift: act as on_drift says (report: the watch logged it already)."""
        action = self.settings.on_drift
        if action == "refit":
            self._drift_refit_from_s = watch.onset_s
            self.get_logger().info(f"drift: a refit follows once {self.settings.drift_refit_record:g} s are "
                                   f"recorded from where the change began ({watch.onset_s:.0f} s)")
        elif action == "excite":
            if self.refitting:
                self.get_logger().warning("drift: no excitation while a refit runs")
                return
            started, message = self.start_excitation(self.settings.drift_excite_duration)
            self._refit_after_excitation = started
            if not started:
                self.get_logger().warning(f"drift: cannot excite: {message}")

    def recent_series(self, from_s: float) -> Series:
        """The watch's recent record from from_s [s of stage time] on, as a checked Series (InputError when it
        cannot support a fit)."""
        t_s, current_a, position_m = self.watch.recent_arrays()
        kept = t_s >= from_s
        return make_series(t_s[kept], current_a[kept], position_m[kept], "the watch's recent record",
                           min_samples=self.settings.min_samples)

    def start_guarded_refit(self, what: str, series: Callable[[], Series], hysteresis_only: bool = False) -> None:
        """Refit what series() gives in the background (hysteresis_only: the model in force's GPI parameters with
        its dynamics held, where it can be); the model in force is replaced only when the new one predicts the
        held-out tail better."""
        reason = self.refusal()
        if reason is not None:
            self.get_logger().warning(f"refit on drift refused: {reason}")
            return

        def work() -> None:
            self.lower_refit_priority()
            try:
                self.guarded_refit(what, series(), hysteresis_only)
            except InputError as error:
                self.get_logger().warning(f"refit on drift refused: {error}")
            except Cancelled:
                self.get_logger().warning("refit on drift cancelled: the node is stopping (nothing pushed)")
            except Exception as error:  # noqa: BLE001 -- a failing fit must not take the node down
                self.get_logger().error(f"refit on drift failed: {type(error).__name__}: "
                                        f"{' '.join(str(error).split())}")
            finally:
                with self._lock:
                    self.refitting = False

        self.refit_service.run_in_background(work)

    def guarded_refit(self, what: str, series: Series, hysteresis_only: bool = False) -> None:
        """Fit series (see start_guarded_refit); push the model if it predicts the held-out tail better than the
        model in force."""
        in_force = self.history.current
        if in_force is None:
            raise InputError("no model in force is known (has the compensator published ~/model?)")
        refusal = dynamics_held_refusal(in_force.model) if hysteresis_only else None
        if hysteresis_only and refusal is None:
            self.get_logger().info(f"refit on drift: the hysteresis of the model in force on {what} ({len(series)} "
                                   "samples), its dynamics held")
            found = refit_hysteresis(series, in_force.model, self.settings.holdout_fraction,
                                     source=f"identification node, hysteresis refit on drift ({what})")
        else:
            self.get_logger().info(f"refit on drift: fitting {what} ({len(series)} samples)"
                                   + (f"; all of it: {refusal}" if refusal else ""))
            found = self.identify(series, f"identification node, refit on drift ({what})")
        decision = judge_swap(found.model, in_force.model, series, found.scored_from)
        report = {**found.report, "swap": {"swapped": decision.swap, "reason": decision.reason,
                                           "candidate": decision.candidate.to_dict(),
                                           "in_force": decision.in_force.to_dict()},
                  "model_file": None, "report_file": None}
        if decision.swap:
            t_s, current_a, _ = self.watch.recent_arrays() if self.watch is not None else ((), (), ())
            model = started_from(found.model, t_s, current_a) if len(t_s) else found.model
            report["model_file"] = self.write_model(model)
            report["report_file"] = report_path(report["model_file"])
            report["compensator"] = self.push(model, f"refit on drift: {decision.reason}")
            if not report["compensator"]["pushed"]:
                report["warnings"].append(report["compensator"]["message"])
            if report["report_file"] is not None:
                self.write_report(report)
        self.publish_report(report)
        self.get_logger().info(f"refit on drift: {decision.reason}")
