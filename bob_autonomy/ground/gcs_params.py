"""The parameter protocol of the ground-station component (`bob_autonomy.ground.gcs`): PARAM_REQUEST_LIST,
PARAM_REQUEST_READ (by id or index) and PARAM_SET, each answered with PARAM_VALUE (the value in force; INT32
values C-cast to float, as ArduPilot does), and how a refused value is told, counted and logged.

`ParameterProtocol` is a mixin of `GcsComponent`, which provides the attributes it declares.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs_codec import GcsCounters, MavlinkCodec
from bob_autonomy.ground.params import ParamError, ParameterStore

logger = logging.getLogger("bob_autonomy.ground.gcs")

REFUSAL_LOG_FIRST = 10  # out-of-range refusals logged one by one; then at most one line per REFUSAL_LOG_PERIOD_S
REFUSAL_LOG_PERIOD_S = 10.0


class ParameterProtocol:
    """The parameter protocol's handlers and the refusal of bad values, mixed into GcsComponent."""

    codec: MavlinkCodec
    counters: GcsCounters
    params: ParameterStore
    clock: Callable[[], float]
    _last_refusal_log_s: float

    # provided by GcsComponent
    def _queue(self, message: mavlink.MAVLink_message) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def notify(self, severity: int, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _statustext(self, severity: int, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _send_param(self, name: str) -> None:
        value = float(self.params.get(name))
        spec = self.params.spec(name)
        self._queue(
            self.codec.mav.param_value_encode(
                name.encode("ascii"), value, spec.mav_type, len(self.params), self.params.index(name)
            )
        )

    def _param_request_list(self, msg) -> None:
        for name in self.params.names():
            self._send_param(name)

    def _param_request_read(self, msg) -> None:
        index = msg.param_index  # -1: by name (MAVLink); otherwise 0 .. count - 1
        if not -1 <= index < len(self.params):
            self._refuse_value(f"PARAM_REQUEST_READ: param_index {index} outside [-1, {len(self.params) - 1}]")
            return
        try:
            name = self.params.name_at(index) if index >= 0 else msg.param_id
            self.params.spec(name)
        except ParamError as exc:
            self.notify(mavlink.MAV_SEVERITY_WARNING, f"PARAM_REQUEST_READ: {exc}")
            return
        self._send_param(name)

    def _param_set(self, msg) -> None:
        name = msg.param_id
        if name not in self.params:
            self.counters.params_rejected += 1
            self.notify(mavlink.MAV_SEVERITY_WARNING, f"PARAM_SET: unknown parameter {name!r}")
            return
        try:
            self.params.set(name, float(msg.param_value))  # checks finite, integral for INT32, in range
        except ParamError as exc:
            self.counters.params_rejected += 1
            self._refuse_value(f"PARAM_SET refused: {exc}")  # names the parameter and says why
        else:
            self.counters.params_set += 1
            self._persist_warning()
        self._send_param(name)

    def _persist_warning(self) -> None:
        if self.params.persist_error:
            self.notify(mavlink.MAV_SEVERITY_ERROR, self.params.persist_error)

    def _refuse_value(self, text: str) -> None:
        """A message refused for a value that is not finite or out of its field's range: counted, told to the
        ground station (STATUSTEXT), logged (the first REFUSAL_LOG_FIRST, then one line per period)."""
        c = self.counters
        c.out_of_range += 1
        self._statustext(mavlink.MAV_SEVERITY_WARNING, text)
        now = float(self.clock())
        if c.out_of_range <= REFUSAL_LOG_FIRST or now - self._last_refusal_log_s >= REFUSAL_LOG_PERIOD_S:
            self._last_refusal_log_s = now
            logger.warning("%s (%d messages refused for out-of-range values so far)", text, c.out_of_range)
