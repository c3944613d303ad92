"""The identification node's excitation: `~/excite` drives the identification signal on current_cmd while the
compensator is paused, `~/abort_excitation` stops it. Mixed into IdentificationNode."""

from __future__ import annotations

from rcl_interfaces.srv import SetParametersAtomically
from rclpy.parameter import Parameter
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.experiment.design import design_schedule
from sma_stage.experiment.probe import ProbeResult, analyse_probe, probe_duration_s, probe_signal
from sma_stage.nodes._common import quiet_on_shutdown
from sma_stage.nodes.identification.params import EXCITATIONS
from sma_stage.signals import joined_by_raised_cosines, paper_identification_signal


class ExcitationRoom:
    """~/excite and ~/abort_excitation, and the excitation's timer (uses the node's settings, lock and publishers)."""

    @property
    def exciting(self) -> bool:
        """True while the identification signal is being driven."""
        return self.excite_timer is not None

    def signal_time_s(self) -> float:
        """Seconds of signal time since the excitation started."""
        return (self.now_ns() - self.excite_start_ns) * 1e-9 * self.settings.excite_time_scale

    def on_excite(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Start driving the identification signal and return at once."""
        response.success, response.message = self.start_excitation(self.settings.excite_duration)
        return response

    def start_excitation(self, duration_s: float) -> tuple[bool, str]:
        """Drive the identification signal for duration_s [s of signal time]: (started, one line saying so or why
        not)."""
        if self.exciting:
            return False, f"an excitation is running ({self.excitation_left_s():.1f} s of signal left)"
        if self.now_ns() == 0:
            return False, ("no time yet: use_sim_time is true and no /clock message has come (is the stage running "
                           "with use_sim_time?); the signal would start part-way through")
        if self.settings.excite_signal not in EXCITATIONS:
            return False, f"excite_signal must be one of {', '.join(EXCITATIONS)}, got {self.settings.excite_signal!r}"
        if self.settings.clear_on_excite:
            self.on_clear(Trigger.Request(), Trigger.Response())
        with self._lock:
            self.record_until_ns = None
        self.excite_start_ns = self.now_ns()
        self.excite_duration_s = duration_s
        self.probe, self.design = None, None
        self.set_compensator_enabled(False)
        self.excite_timer = self.create_timer(1.0 / self.settings.excite_rate_hz,
                                              quiet_on_shutdown(self, self.on_excite_tick))
        self.on_excite_tick()
        if self.settings.excite_signal == "designed":
            message = (f"exciting: the probe ({probe_duration_s(duration_s):g} s) and the signal designed from what "
                       f"it finds, up to {self.settings.excite_amplitude_start:g} A, {duration_s:g} s of signal time")
        else:
            message = (f"exciting: {self.settings.excite_amplitude_start:g} A falling to "
                       f"{self.settings.excite_amplitude_end:g} A, period {self.settings.excite_period:g} s, "
                       f"{duration_s:g} s of signal time")
        self.get_logger().info(message)
        return True, message

    def excitation_left_s(self) -> float:
        """Seconds of signal time the excitation still runs."""
        return max(self.excite_duration_s - self.signal_time_s(), 0.0)

    def on_excite_tick(self) -> None:
        """Publish the signal's current value; at the end publish zero and stop."""
        if self.excite_timer is None:
            return
        t = self.signal_time_s()
        duration = self.excite_duration_s
        if t >= duration:
            self.command_pub.publish(Float64(data=0.0))
            self.stop_excitation()
            frozen = self.settings.freeze_after_excite
            with self._lock:
                self.record_until_ns = self.now_ns() if frozen else None
            if self._refit_after_excitation:
                self._refit_after_excitation = False
                self.get_logger().info("excitation on drift finished: refitting it")
                self.start_guarded_refit("the excitation on drift", self.snapshot)
                return
            self.get_logger().info("excitation finished: ~/refit can fit it now"
                                   + (" (buffer frozen until ~/clear or ~/excite)" if frozen else ""))
            return
        if self.settings.excite_signal == "designed":
            value = self.designed_value(t)
            if value is None:
                return
        else:
            value = paper_identification_signal(t, self.settings.excite_amplitude_start,
                                                self.settings.excite_amplitude_end,
                                                self.settings.excite_period, duration)
        self.command_pub.publish(Float64(data=float(value)))

    def designed_value(self, t: float) -> float | None:
        """The designed excitation's current [A] at signal time t [s]: the probe's, then, once the probe has ended
        and what it recorded is analysed, the design's; None when the probe found nothing to design on (the
        excitation is then stopped at 0 A and the log says why)."""
        limit, probe_s = self.settings.excite_amplitude_start, probe_duration_s(self.excite_duration_s)
        if t < probe_s:
            return float(probe_signal(t, limit, probe_s))
        if self.design is None:
            try:
                self.probe = self.analyse_recorded_probe(probe_s)
                self.design = design_schedule(self.probe, self.excite_duration_s - probe_s, self.settings.excite_seed)
            except InputError as error:
                self.command_pub.publish(Float64(data=0.0))
                self.stop_excitation()
                self.get_logger().error(f"excitation stopped after the probe: {error}")
                return None
            self.get_logger().info(f"the probe found: {self.probe.summary()}")
        return float(joined_by_raised_cosines(t - probe_s, *self.design))

    def analyse_recorded_probe(self, probe_s: float) -> ProbeResult:
        """What the probe found, from the last probe_s seconds (stage time) of the recording."""
        series = self.recording_snapshot(min_samples=20)
        keep = series.t >= series.t[-1] - probe_s
        return analyse_probe(series.t[keep], series.input[keep], series.output[keep])

    def on_abort_excitation(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Stop a running excitation now: current_cmd 0 A, the compensator enabled again; the buffer keeps what
        was recorded and records on (not frozen)."""
        if not self.exciting:
            response.success, response.message = False, "no excitation is running"
            return response
        done, duration = self.signal_time_s(), self.excite_duration_s
        self._refit_after_excitation = False
        self.command_pub.publish(Float64(data=0.0))
        self.stop_excitation()
        response.success = True
        response.message = (f"excitation aborted after {done:.1f} of {duration:g} s of signal: current_cmd 0 A, "
                            "current_cmd handed back to the compensator; the buffer keeps what was recorded")
        self.get_logger().warning(response.message)
        return response

    def stop_excitation(self) -> None:
        """Stop the excitation timer (the current stays at the last value published) and hand current_cmd
        back to the compensator."""
        timer, self.excite_timer = self.excite_timer, None
        if timer is not None:
            self.destroy_timer(timer)
            self.set_compensator_enabled(True)

    def set_compensator_enabled(self, enabled: bool) -> None:
        """Ask the compensator to publish again or to keep silent (pause_compensator); answers are logged,
        not awaited (a service callback must not block)."""
        if not self.settings.pause_compensator or not self.context.ok():
            return
        name = self.push_client.srv_name
        if not self.push_client.service_is_ready():
            if not enabled:
                self.get_logger().warning(f"{name} not available: a compensator may publish during the excitation")
            return
        request = SetParametersAtomically.Request(parameters=[Parameter("enabled", value=enabled).to_parameter_msg()])
        future = self.push_client.call_async(request)

        def answered(done: object) -> None:
            result = done.result()
            if result is None or not result.result.successful:
                self.get_logger().warning(f"{name} did not take enabled={enabled}: "
                                          f"{result.result.reason if result is not None else 'no answer'}")

        future.add_done_callback(answered)
