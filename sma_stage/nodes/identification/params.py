"""The identification node's parameters (every one with its description and range) and the checks across them."""

from __future__ import annotations

from sma_stage.errors import InputError
from sma_stage.identify.families import FAMILIES
from sma_stage.identify.pipeline import FIT_SAMPLES
from sma_stage.identify.workers import MAX_NICENESS, WORKER_NICENESS
from sma_stage.model.parameters import MAX_OPERATORS
from sma_stage.nodes._common import JOINT_NAME, Param, Settings, settings_type

EXCITATIONS = ("paper", "designed")
ON_DRIFT = ("report", "refit", "excite")
DRIFT_REFIT_SCOPES = ("hysteresis", "full")
STORAGES = ("sqlite3", "mcap")
DIAGNOSTICS_PERIOD_S = 1.0

IDENTIFICATION_PARAMS = [
    Param("max_samples", 400000, "ring buffer length per topic [messages; an hour at 100 Hz is 360,000]; the oldest "
          "are dropped", 100, 10**8,
          read_only=True),
    Param("min_samples", 100, "fewest aligned samples a refit accepts", 20, 10**8),
    Param("holdout_fraction", 0.25, "tail of the recording held out for validation", 0.05, 0.5),
    Param("validation_files", "", "further validation records for ~/refit, comma-separated (CSV t,input,output or "
          "rosbag2 directories, each run from an idle stage): every family is scored on them too and chosen on the "
          "record it predicts worst; empty: the held-out tail alone"),
    Param("max_fit_samples", FIT_SAMPLES, "a longer recording is fitted on a copy thinned by whole blocks to at most "
          "this many samples, scored on every sample (0: never thin)", 0, 10**8),
    Param("operators", 10, "play operators of the fitted model (0: chosen by the fit)", 0, MAX_OPERATORS),
    Param("diagnose_rounds", 1, "rounds of residual diagnosis after the fit (0: none); the effects it adds are "
          "in the model written and pushed", 0, 4),
    Param("diagnose_workers", 1, "processes fitting a diagnosis round's candidates at once (1: in this node's "
          "process; more finish sooner and take CPU from a stage on the same computer)", 1, 64),
    Param("refit_niceness", WORKER_NICENESS, "nice levels a refit's thread and its worker processes run below the "
          "node's other threads (Linux), so that a stage on the same computer keeps its cycles; 0: at the node's "
          "priority (a computer that only identifies)", 0, MAX_NICENESS),
    Param("families", list(FAMILIES), "model families ~/refit fits on the same recording (default: gpi, gpi_free, "
          "two_wire, bouc_wen; two_wire_compact when named); the one with the lowest held-out error (then BIC) is written and pushed, and the "
          "compensator runs it"),
    Param("model_file", "", "where ~/refit writes the fitted model (atomically); empty: not written"),
    Param("compensator_name", "compensator", "node that receives the fitted parameters (relative or absolute)",
          read_only=True),
    Param("max_held_out_rms_pct", 10.0, "a refit whose model misses the held-out tail by more than this RMS [% of the "
          "recording's span] is refused: nothing written or pushed (a recording cut short, a stage that stopped)",
          0.1, 1000.0),
    Param("push_timeout", 2.0, "wait for the compensator's parameter service [s]", 0.0, 60.0),
    Param("pause_compensator", True, "set the compensator's enabled false while ~/excite drives the stage, so "
          "one node at a time owns current_cmd"),
    Param("record_bag", "", "rosbag2 directory to record input_topic and joint_states into; empty: none"),
    Param("bag_storage", "mcap", f"rosbag2 storage: {' or '.join(STORAGES)} (mcap: Foxglove and PlotJuggler open it)"),
    Param("bag_overwrite", False, "replace an existing record_bag directory (when the bag is finished)"),
    Param("excite_signal", "paper", "identification signal: paper (the decaying sine) or designed (a probe of each "
          "wire's band and lag, a tenth of excite_duration, then reversal curves over the band it found, up to "
          "excite_amplitude_start; see gpi_tool excitation)"),
    Param("excite_seed", 0, "the designed signal's draw", 0, 2**31 - 1),
    Param("excite_amplitude_start", 5.0, "identification signal amplitude at its start [A] (designed: its "
          "largest current)", 0.0, 20.0),
    Param("excite_amplitude_end", 3.6, "identification signal amplitude at its end [A]", 0.0, 20.0),
    Param("excite_period", 250.0, "identification signal period [s of signal time]", 0.001, 1e6),
    Param("excite_duration", 1000.0, "identification signal length [s of signal time]", 0.001, 1e7),
    Param("excite_rate_hz", 50.0, "identification signal publication rate [Hz]", 1.0, 2000.0),
    Param("excite_time_scale", 1.0, "stage seconds per node-clock second (the stage's time_scale without "
          "use_sim_time; 1 with it): the excitation's signal time and the recording's time axis, so that the "
          "model refitted counts stage seconds", 0.001, 10000.0),
    Param("clear_on_excite", True, "empty the buffer when ~/excite starts, so a refit sees only the excitation"),
    Param("freeze_after_excite", True, "stop filling the buffer when an excitation ends (until ~/clear or "
          "~/excite), so a refit sees only the excitation; the bag records on"),
    Param("joint_name", JOINT_NAME, "joint of joint_states that carries the stage position", read_only=True),
    Param("watch", True, "watch the compensator's model against the stage: ~/residual and a /diagnostics status",
          read_only=True),
    Param("watch_window", 10.0, "the watch's window [s of stage time]: the drift tests look at the residual per "
          "window", 1.0, 3600.0, read_only=True),
    Param("watch_warmup_windows", 30, "windows after a model goes in force that are not counted (it and the stage settle "
          "from what came before: an excitation leaves the wires warm for minutes)", 0, 1000, read_only=True),
    Param("watch_calibration_windows", 120, "windows after the warm-up that measure the model's residual: its level and "
          "where along the stage's path it is what (the path test's memory)", 1, 100000, read_only=True),
    Param("watch_shift_allowance", 0.1, "path test: where the stage retraces its path, a residual moved by up to this "
          "fraction of the reference counts as no change", 0.0, 10.0, read_only=True),
    Param("watch_shift_threshold", 0.3, "path test: drift when the CUSUM of the moved fraction less the allowance "
          "exceeds this", 0.01, 100.0, read_only=True),
    Param("watch_bias_allowance", 1.5, "path test: where the stage retraces its path, a window's mean residual moved "
          "by up to this many standard errors (from how it wandered there while calibrating) counts as no change",
          0.0, 100.0, read_only=True),
    Param("watch_bias_threshold", 3.0, "path test: drift when the CUSUM of the mean's standard errors less the "
          "allowance exceeds this", 0.01, 1000.0, read_only=True),
    Param("watch_path_radius", 0.2, "path test: how near a remembered path [its standard deviations] counts as the "
          "same path", 0.001, 10.0, read_only=True),
    Param("watch_allowance", 1.5, "level test: windows up to this times the largest calibration window count as no "
          "change", 1.0, 100.0, read_only=True),
    Param("watch_threshold", 1.5, "level test: drift when the CUSUM of ln(window RMS / (allowance x largest)) "
          "exceeds this", 0.1, 100.0, read_only=True),
    Param("watch_record", 900.0, "recent samples the watch keeps [s of stage time]: what a refit on drift fits and "
          "where a model swapped in starts", 60.0, 86400.0, read_only=True),
    Param("on_drift", "report", "what the watch's drift does: report (log it), refit (fit the recent record and swap "
          "only if the new model predicts its held-out tail better), excite (stop tracking, excite "
          "drift_excite_duration, then the same on that)"),
    Param("drift_refit_record", 600.0, "on_drift refit: the refit waits for this much of the record from where the "
          "change began, and fits that [s of stage time; at most watch_record]", 60.0, 86400.0),
    Param("drift_refit_scope", "hysteresis", "on_drift refit, on the tracking record: hysteresis (refit the GPI "
          "parameters with the model in force's thermal dynamics held; a full identification for a model that is "
          "not a GPI with input effects only) or full (identify everything again, as ~/refit)"),
    Param("drift_excite_duration", 300.0, "on_drift excite: the excitation's length [s of signal time]", 1.0, 1e6),
    Param("model_history", 5, "models in force kept, newest last (~/rollback restores the one before)", 2, 1000,
          read_only=True),
    Param("input_from_effort", True, "record, refit and watch the current [A] from joint_states' effort, stamped "
          "with the position it led to (as the stage node publishes it), when every message carries it; false, or "
          "a stage without it: input_topic, timed by its arrival", read_only=True),
    Param("input_topic", "current_applied", "std_msgs/Float64 topic of the current recorded and fitted [A]: what "
          "the stage applied (current_cmd for a stage that does not publish it, or a bag of commands)",
          read_only=True),
]



IdentificationSettings = settings_type("IdentificationSettings", IDENTIFICATION_PARAMS)


def check_drift_settings(values: Settings) -> None:
    """Refuse an on_drift this node does not know, or a drift refit's record longer than the watch keeps."""
    if values.on_drift not in ON_DRIFT:
        raise InputError(f"on_drift must be one of {', '.join(ON_DRIFT)}, got {values.on_drift!r}")
    if values.drift_refit_scope not in DRIFT_REFIT_SCOPES:
        raise InputError(f"drift_refit_scope must be one of {', '.join(DRIFT_REFIT_SCOPES)}, got "
                         f"{values.drift_refit_scope!r}")
    if values.drift_refit_record > values.watch_record:
        raise InputError(f"drift_refit_record {values.drift_refit_record:g} s is longer than the watch keeps "
                         f"(watch_record {values.watch_record:g} s)")

def check_storage(storage: str) -> None:
    """Refuse a rosbag2 storage this node cannot write."""
    if storage not in STORAGES:
        raise InputError(f"bag_storage must be one of {', '.join(STORAGES)}, got {storage!r}")
