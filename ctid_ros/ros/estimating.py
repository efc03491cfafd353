"""
The node's estimates: one window in, an :class:`~ctid_ros.streaming.session.Update` out.

:meth:`Estimating.estimate` takes the latest window from the
:class:`~ctid_ros.streaming.buffer.SampleBuffer` and calls
:meth:`~ctid_ros.streaming.session.IdentificationSession.update`; it runs in the estimation
thread (:mod:`ctid_ros.ros.worker`) or for ``~/estimate_now``, one at a time (the estimation
lock). Without a window it says why: warming up against the configured window, a gap, a
silent stream (a dead publisher would otherwise have its last window estimated again and
again).

Change alarm: every estimate also goes to a :class:`~ctid_ros.streaming.alarm.ChangeDetector`
(the one ``ctid replay --sliding`` uses). ``~/capture_baseline`` averages the last
``baseline_windows`` windows into the baseline and writes ``baseline_file``; ``~/reset``
clears the buffer, the warm start and the alarm's sums and keeps its baseline.

:class:`Estimating` is the part of the identification node that does this; it reads the
configuration, buffer, session and detector under ``_lock`` and keeps ``last_update``.
"""

import math
import time
from typing import Any, Dict, Optional, Tuple

from ctid_ros.design.tune import tune_from_settings
from ctid_ros.errors import ConfigError, CtidError, DataError
from ctid_ros.estimation.compare import compare
from ctid_ros.ros.output import ERROR_LOG_PERIOD
from ctid_ros.streaming.alarm import AlarmSettings, ChangeDetector
from ctid_ros.streaming.baseline import Baseline, write_baseline_file
from ctid_ros.streaming.buffer import Gap, SampleBuffer
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import (comparison_message, estimate_summary, failure_status,
                                         NANOSECONDS, OK, tuning_message, update_status,
                                         warm_up_text, WARN)
from ctid_ros.streaming.sampler import ROLES
from ctid_ros.streaming.session import IdentificationSession, Update
from std_srvs.srv import Trigger

__all__ = ['Estimating']

# The key of the tuning's note on /diagnostics and of its warning logged once.
_TUNING = 'tuning'
_COMPARISON = 'comparison'
# A capture whose windows scatter more than this (in variance, against their covariance) is
# reported with a warning: the plant was probably changing.
_SCATTER_LIMIT = 9.0


class Estimating:
    """
    Estimating on the latest window, reporting why not, and the alarm's services.

    A part of :class:`~ctid_ros.ros.node.IdentificationNode`, not usable alone.
    """

    def estimate(self, started: Optional[float] = None) -> Tuple[Optional[Update], str]:
        """
        Estimate on the latest window now and publish the result and diagnostics.

        Parameters
        ----------
        started : float, optional
            ``time.perf_counter()`` of the request (the timer tick), for ``publish_latency``.

        Returns
        -------
        (Update or None, str)
            The update (None if there was none) and a one-line summary or the reason.

        """
        started = time.perf_counter() if started is None else started
        with self._estimation_lock:
            with self._lock:
                config, buffer, session = self._config, self._buffer, self._session
                detector, pending = self._detector, self._pending_baseline
                self._pending_baseline = None
            if config is None:
                return None, 'not configured'
            if session.config is not config:
                session.reconfigure(config)
            self._follow_configuration(detector, config, pending)
            try:
                self._check_silence(config, buffer)
            except DataError as error:
                return None, self._failed(error)
            try:
                window = session.take_window(buffer)
            except DataError as error:
                return None, self._no_window(config, buffer, session, error)
            try:
                update = session.update(window)
            except CtidError as error:
                return None, self._failed(error)
            finally:
                self._worker.spent(started)
            previous = detector.status
            alarm = detector.update(update)
        self.last_update = update
        self._estimated_since_start = True
        self._publish(update, config)
        current = self._config
        if current is not config and current is not None:
            # The model changed while this estimate ran: its ~/params/<old name> go again.
            self._follow_outputs(current)
        values = update.diagnostics()
        values['publish_latency'] = time.perf_counter() - started
        origin = self._origin_ns if self._origin_ns is not None else update.start_ns
        values['time'] = (update.end_ns - origin) / NANOSECONDS
        values['window'] = config.window
        values.update(alarm.diagnostics(origin))
        values.update(self._tune(update, config, values['time']))
        values.update(self._compare(update, config, values['time']))
        # The tuning and the comparison count in the estimate's share of the CPU.
        self._worker.spent(started)
        self._publish_alarm(alarm)
        self._log_alarm(previous, alarm)
        level, text = update_status(update.names, update.values, update.stds, values)
        available = self._available(buffer)
        if available is not None and available < config.window:
            text = f'{warm_up_text(available, config.window)}; {text}'
        skipped = self._worker.skipped_since_estimate
        if skipped:
            level = max(level, WARN)
            text = (f'{skipped} tick(s) skipped: an estimate takes {update.compute_time:.3g} s '
                    f'and the node keeps half a core free; {text}')
            self._worker.skipped_since_estimate = 0
        self._publish_status(level, text, values)
        self._log_estimate(update, values['time'])
        return update, estimate_summary(update.names, update.values, update.stds)

    def _tune(self, update: Update, config: IdentificationConfig, time_s: float
              ) -> Dict[str, Any]:
        """
        Tune ``tune.controller`` on the estimate and publish it on ``~/tuning`` (latched).

        Returns the values it adds to ``/diagnostics``. A design the model does not allow
        (e.g. SIMC on an unstable model) is logged as a warning once per change of its text
        and shown on ``/diagnostics`` until a tuning succeeds; the last recommendation
        published stays on the topic.
        """
        settings = config.tune_settings()
        if settings is None:
            with self._lock:
                self._notes.pop(_TUNING, None)
            return {}
        try:
            tuning = tune_from_settings(update.result, settings)
        except CtidError as error:
            text = f'tuning {config.tune_controller} failed: {error}'
            self._log_once(_TUNING, text, error=False)
            with self._lock:
                self._notes[_TUNING] = text
            return {}
        with self._lock:
            self._notes.pop(_TUNING, None)
            self._logged.pop(_TUNING, None)
        recommendation = {'time': time_s, 'model': update.result.model.expression,
                          **tuning.to_dict(config.tune_joint)}
        self._outputs.send(tuning_message(self._node_topics, recommendation))
        gains = tuning.gains.to_dict()
        return {'tuning': ', '.join(f'{name} {value:.4g}' for name, value in gains.items()),
                'tuning_ms': tuning.margins.ms,
                'tuning_unstable_draws': f'{tuning.unstable_draws} of {tuning.draws}'}

    def _compare(self, update: Update, config: IdentificationConfig, time_s: float
                 ) -> Dict[str, Any]:
        """
        Every ``compare_every`` estimates, compare ``candidate_models`` on the window.

        Publishes the ranking on ``~/model_recommendation`` (latched) and returns the values
        it adds to ``/diagnostics``; a comparison that fails is reported as the tuning is.
        """
        if not config.candidate_models:
            self._estimates_since_comparison = 0
            with self._lock:
                self._notes.pop(_COMPARISON, None)
            return {}
        self._estimates_since_comparison += 1
        if self._estimates_since_comparison < config.compare_every:
            return {}
        self._estimates_since_comparison = 0
        try:
            comparison = compare(config.candidate_models, update.window.data,
                                 **config.compare_options())
        except CtidError as error:
            text = f'comparing candidate_models failed: {error}'
            self._log_once(_COMPARISON, text, error=False)
            with self._lock:
                self._notes[_COMPARISON] = text
            return {}
        with self._lock:
            self._notes.pop(_COMPARISON, None)
            self._logged.pop(_COMPARISON, None)
        best = comparison.recommended
        self._outputs.send(comparison_message(self._node_topics, {
            'time': time_s, 'recommended': best.model.expression,
            'candidates': [candidate.to_dict() for candidate in comparison.candidates]}))
        return {'recommended_model': best.model.expression, 'recommended_why': best.why}

    def _follow_configuration(self, detector: ChangeDetector, config: IdentificationConfig,
                              pending: Optional[Tuple[Optional[Baseline], str]]) -> None:
        """Bring the detector to ``config`` and a baseline set at runtime (estimation lock)."""
        settings = AlarmSettings.from_config(config)
        if settings != detector.settings:
            detector.reconfigure(settings, None if pending is None else pending[0])
        elif pending is not None:
            detector.set_baseline(pending[0])
        if pending is not None:
            self.get_logger().info(self._baseline_line(*pending))

    def _baseline_line(self, baseline: Optional[Baseline], note: str) -> str:
        if baseline is None:
            return f'change alarm: {note}; set baseline.<name> or call ~/capture_baseline'
        config = self._config
        return (f'change alarm: baseline {note}: {baseline.describe()}; '
                f'{config.false_alarm_per_hour:g} false alarms per hour')

    def _origin(self) -> int:
        return self._origin_ns if self._origin_ns is not None else 0

    @staticmethod
    def _available(buffer: SampleBuffer) -> Optional[float]:
        """Return the seconds covered by both streams without a gap, or None if unknown."""
        stats = buffer.stats()
        if stats.u.gaps or stats.y.gaps:
            return None
        try:
            first, last = buffer.coverage()
        except DataError:
            return None
        return (last - first) / NANOSECONDS

    def _no_window(self, config: IdentificationConfig, buffer: SampleBuffer,
                   session: IdentificationSession, error: DataError) -> str:
        """
        Report why there is no window to estimate on.

        Collecting the first half window: OK, ``warming up: 1.2 of 4 s of data``, against the
        configured window. Collecting it again after a gap: WARN, the same with the gaps (in
        seconds since the first sample). Anything else (no samples): WARN with the error.
        """
        needed = 0.5 * config.window
        try:
            latest = buffer.window(session.window_length(), config.sample_time,
                                   min_length=2 * config.sample_time)
            available, gaps = len(latest.data) * config.sample_time, latest.gaps
        except DataError:
            # Not even two grid instants yet: the span both streams cover, if they have data.
            available, gaps = self._available(buffer), ()
        if available is None or available >= needed:
            return self._failed(error)
        text = warm_up_text(available, config.window, needed)
        values = {'window': config.window, 'data': available}
        if not gaps and not self._estimated_since_start:
            self._publish_status(OK, text, values)
            return text
        gaps = '; '.join(map(self._describe_gap, gaps)) or 'data missing before'
        text = f'{text}, again after a gap: {gaps}'
        self.get_logger().warning(f'no estimate: {text}', throttle_duration_sec=ERROR_LOG_PERIOD)
        self._publish_status(WARN, text, values)
        return text

    def _describe_gap(self, gap: Gap) -> str:
        origin = (self._origin_ns or 0) / NANOSECONDS
        if gap.end is None:
            return f'{gap.stream} silent since t={gap.start - origin:.2f} s'
        return (f'{gap.stream} missing for {gap.duration:.3g} s from t={gap.start - origin:.2f} '
                's')

    def _check_silence(self, config: IdentificationConfig, buffer: SampleBuffer) -> None:
        """
        Refuse to estimate again from stale data when a stream stopped.

        The buffer's windows end at its newest data, so without this check a dead publisher
        would go unnoticed: the same last window would be estimated over and over.
        """
        now = self.get_clock().now().nanoseconds
        limit = max(config.max_gap, config.update_period)
        for role, name in zip(ROLES, buffer.names):
            last = self._counters.last_received[role]
            if last is not None and now - last > limit * NANOSECONDS:
                silence = (now - last) / NANOSECONDS
                raise DataError(f'{name} silent: no message for {silence:.3g} s (more than '
                                f'{limit:g} s); check its publisher')

    def _failed(self, error: CtidError) -> str:
        level, text = failure_status(error)
        self.get_logger().warning(f'no estimate: {text}', throttle_duration_sec=ERROR_LOG_PERIOD)
        self._publish_status(level, text, {})
        return text

    # Services ------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget all samples, counters, the warm start and the alarm's sums (not its baseline)."""
        with self._estimation_lock, self._lock:
            if self._buffer is not None:
                self._buffer.clear()
                self._session.reset()
                self._detector.reset()
            self._restart_counters()
        if self._detector is not None:
            self._publish_alarm(self._detector.status)

    def capture_baseline(self) -> Tuple[bool, str]:
        """
        Average the last ``baseline_windows`` windows into the baseline; save it if configured.

        Returns
        -------
        (bool, str)
            Whether a baseline was captured, and what happened (the values, where they were
            written, or why not).

        """
        with self._estimation_lock:
            with self._lock:
                detector, config = self._detector, self._config
            if detector is None:
                return False, 'not configured'
            origin = self._origin()
            windows = list(detector.recent_ends())
            try:
                baseline = detector.capture()
            except DataError as error:
                return False, str(error)
            spread = detector.spread()
        first, last = ((windows[-config.baseline_windows] - origin) / NANOSECONDS,
                       (windows[-1] - origin) / NANOSECONDS)
        note = (f'captured by {self.get_fully_qualified_name()} from {config.baseline_windows} '
                f'windows ending t={first:.2f} to {last:.2f} s (stamps '
                f'{windows[-config.baseline_windows] / NANOSECONDS!r} to '
                f'{windows[-1] / NANOSECONDS!r})')
        text = f'baseline {baseline.describe()}, {note}'
        if spread > _SCATTER_LIMIT:
            text += (f'; warning: the windows scatter {math.sqrt(spread):.3g} times more than '
                     'their covariance says: was the plant changing?')
        if config.baseline_file:
            try:
                path = write_baseline_file(config.baseline_file, baseline,
                                           self.get_fully_qualified_name(), note)
                text += f'; saved to {path}'
            except ConfigError as error:
                text += f'; NOT saved: {error}'
                self.get_logger().error(f'~/capture_baseline: {error}')
        else:
            text += '; not saved (no baseline_file): a restart forgets it'
        self.get_logger().info(f'change alarm: {text}')
        self._publish_alarm(detector.status)
        return True, text

    def _capture_baseline(self, request: Trigger.Request,
                          response: Trigger.Response) -> Trigger.Response:
        try:
            response.success, response.message = self.capture_baseline()
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('capture_baseline', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response

    def _reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.reset()
            response.success, response.message = True, 'buffer cleared, warm start forgotten'
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('reset', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response

    def _estimate_now(self, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        try:
            if not self._active:
                update, response.message = None, 'the node is not active'
            else:
                update, response.message = self.estimate()
            response.success = update is not None
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('estimate_now', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response
