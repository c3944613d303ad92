"""The identification node's refit: `~/refit` fits the recording, writes the model and its report, pushes the
model to the compensator; the report's one-line summary. Mixed into IdentificationNode."""

from __future__ import annotations

import threading
from pathlib import Path

from rcl_interfaces.srv import SetParametersAtomically
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Cancelled
from sma_stage.identify.pipeline import (
    Identification,
    deployed_held_out,
    identify_recording,
)
from sma_stage.identify.workers import lower_priority
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.load import load_series
from sma_stage.io.plain import strict_json
from sma_stage.io.series import Series
from sma_stage.model.kinds import AnyModel
from sma_stage.nodes.identification.recording import recording_series


def report_json(report: dict) -> str:
    """The refit's report as strict JSON (non-finite numbers as null)."""
    return strict_json(report)


def report_path(model_file: str | None) -> str | None:
    """Where the refit's report goes: beside the model file, `<model file without .yaml>.report.json`."""
    if model_file is None:
        return None
    path = Path(model_file)
    return str(path.with_name(path.name.removesuffix(".yaml").removesuffix(".yml") + ".report.json"))


def refit_summary(report: dict) -> str:
    """~/refit's one-line answer: the effects named, the held-out error before and after, where the model and
    the report went, whether the compensator took the model, and the warnings."""
    diagnosis = report.get("diagnosis")
    validation = report["validation"]
    if diagnosis is not None:
        named = ", ".join(diagnosis["effects"]) or "no effect"
        before = diagnosis["before"]["validation"]["rms_pct"]
        after = diagnosis["after"]["validation"]["rms_pct"]
        error = f"{named} added; held-out RMS {before:.3g} % -> {after:.3g} %"
    else:
        error = f"no diagnosis; held-out RMS {validation['rms_pct']:.3g} %"
    parts = [f"refit ok: {report['gpi_fit']['operators']} operators, {error}"]
    families = report.get("families")
    if families:
        scores = ", ".join(f"{row['family']} {row['validation']['rms_pct']:.3g} %" if row["validation"] else
                           f"{row['family']} not fitted" for row in families)
        chosen = [row["family"] for row in families if row["chosen"]]
        parts.append(f"family {chosen[0] if chosen else 'gpi'} deployed (held-out RMS: {scores})")
    parts += [f"model {report['model_file'] or 'not written (model_file empty)'}",
             f"report {report['report_file'] or 'on ~/report only'}",
             "pushed to the compensator" if report["compensator"]["pushed"] else "NOT pushed to the compensator"]
    parts += [f"warning: {warning}" for warning in report["warnings"]]
    return "; ".join(parts)



class RefitRoom:
    """~/refit, the model written and pushed (uses the node's values, lock, recording and clients)."""

    def refusal(self) -> str | None:
        """Why a refit cannot start now (None when it can), and mark it running otherwise."""
        with self._lock:
            if self.exciting:
                return (f"an excitation is running ({self.excitation_left_s():.1f} s of signal left): "
                        "call ~/refit after it ends")
            if self.refitting:
                return "a refit is already running"
            self.refitting = True
            return None

    def snapshot(self) -> Series:
        """The recording so far as a checked Series (InputError when it cannot support a fit)."""
        return self.recording_snapshot(self.settings.min_samples)

    def recording_snapshot(self, min_samples: int) -> Series:
        """The recording so far, aligned as a bag of it would be, with at least min_samples samples."""
        with self._lock:
            inputs, outputs = list(self.inputs), list(self.outputs)
        return recording_series(inputs, outputs, min_samples, self.settings.input_topic,
                                self.settings.excite_time_scale, self.settings.input_from_effort)

    def on_refit(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Fit the recording (in the refit worker thread) and answer with the JSON report."""
        reason = self.refusal()
        if reason is not None:
            response.success, response.message = False, reason
            self.get_logger().warning(f"~/refit refused: {reason}")
            return response
        try:
            report = self.refit()
        except InputError as error:
            response.success, response.message = False, f"refit refused: {error}"
            self.get_logger().warning(response.message)
            return response
        except Cancelled:
            response.success, response.message = False, "refit cancelled: the node is stopping (nothing written)"
            self.get_logger().warning(f"~/{response.message}")
            return response
        except Exception as error:  # noqa: BLE001 -- a failing fit must not take the node down
            response.success = False
            response.message = f"refit failed: {type(error).__name__}: {' '.join(str(error).split())}"
            self.get_logger().error(response.message)
            return response
        finally:
            with self._lock:
                self.refitting = False
        self.publish_report(report)
        response.success, response.message = True, refit_summary(report)
        self.get_logger().info(f"~/refit: {response.message}")
        return response

    def identify(self, series: Series, source: str) -> Identification:
        """The identification pipeline on series with this node's settings (held-out tail, operators,
        diagnosis, families, thinning)."""
        return identify_recording(series, holdout_fraction=self.settings.holdout_fraction,
                                  more_validation=self.validation_records(),
                                  operators=self.settings.operators or None,
                                  diagnose_rounds=self.settings.diagnose_rounds, source=source,
                                  workers=self.settings.diagnose_workers,
                                  families=self.settings.families,
                                  max_fit_samples=self.settings.max_fit_samples,
                                  niceness=self.refit_niceness())

    def validation_records(self) -> list[Series]:
        """The records validation_files names, read now; InputError naming the file that cannot be read."""
        records = []
        for path in (part.strip() for part in self.settings.validation_files.split(",")):
            if path:
                try:
                    records.append(load_series(path, joint_name=self.settings.joint_name))
                except InputError as error:
                    raise InputError(f"validation_files: {path}: {error}") from None
        return records

    def refit_niceness(self) -> int:
        """Nice levels a refit's thread and its worker processes run below the node's other threads."""
        return self.settings.refit_niceness

    def lower_refit_priority(self) -> None:
        """The calling thread (a refit's) refit_niceness levels down: a stage on the same computer keeps its cycles."""
        lower_priority(thread=True, niceness=self.refit_niceness())

    def refit(self) -> dict:
        """Identify, write the model file, push the model; the report (InputError when refused). Runs
        refit_niceness levels below the node's other threads (a stage on the same computer keeps its cycles)."""
        self.lower_refit_priority()
        series = self.snapshot()
        self.get_logger().info(f"~/refit: fitting {len(series)} samples")
        found = self.identify(series, "identification node ~/refit")
        report = found.report
        if self.probe is not None:
            report["probe"] = self.probe.as_dict()
        self.check_held_out(report, series)
        report["model_file"] = self.write_model(found.model)
        report["report_file"] = report_path(report["model_file"])
        report["compensator"] = self.push(found.model, "~/refit")
        if not report["compensator"]["pushed"]:
            report["warnings"].append(report["compensator"]["message"])
        if report["report_file"] is not None:
            self.write_report(report)
        return report

    def check_held_out(self, report: dict, series: Series) -> None:
        """InputError when the model to deploy misses the held-out tail by more than max_held_out_rms_pct."""
        held_out = deployed_held_out(report) or {}
        rms_pct, limit = held_out.get("rms_pct"), self.settings.max_held_out_rms_pct
        if rms_pct is not None and rms_pct > limit:
            raise InputError(f"the model misses the held-out tail by {rms_pct:.3g} % RMS, more than "
                             f"max_held_out_rms_pct {limit:g} % (recording: {len(series)} samples over "
                             f"{series.t[-1] - series.t[0]:.3g} s): the model in force stays")

    def write_report(self, report: dict) -> None:
        """Write the JSON report beside the model file, atomically; a failure is a warning in the report."""
        try:
            atomic_write_text(report["report_file"], report_json(report) + "\n")
        except OSError as error:
            report["warnings"].append(f"cannot write {report['report_file']}: {error.strerror or error}")
            report["report_file"] = None

    def write_model(self, model: AnyModel) -> str | None:
        """Write the identified model's file atomically (None when model_file is empty)."""
        path = self.settings.model_file
        if not path:
            return None
        try:
            model.save(path)
        except OSError as error:
            raise InputError(f"cannot write model_file {path}: {error.strerror or error}") from None
        return path

    def push(self, model: AnyModel, reason: str) -> dict:
        """Send the whole model to the compensator as one atomic parameter change (its `model`); reason: why, for
        the history."""
        self._push_reason = reason
        outcome = self._push(model)
        if not outcome["pushed"]:
            self._push_reason = None
        return outcome

    def _push(self, model: AnyModel) -> dict:
        name = self.push_client.srv_name
        if not self.push_client.wait_for_service(timeout_sec=self.settings.push_timeout):
            return {"pushed": False, "message": f"compensator service {name} not available: model not pushed"}
        parameters = [Parameter("model", value=model.to_yaml_text()).to_parameter_msg()]
        future = self.push_client.call_async(SetParametersAtomically.Request(parameters=parameters))
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(max(self.settings.push_timeout, 1.0)) or future.result() is None:
            return {"pushed": False, "message": f"no answer from {name}: the model may not be in force"}
        result = future.result().result
        if not result.successful:
            return {"pushed": False, "message": f"compensator refused the model: {result.reason}"}
        return {"pushed": True, "message": f"model set through {name}"}
