"""The MAVLink parameter protocol against the stack's live parameters (the table: params.py):
PARAM_REQUEST_LIST / PARAM_REQUEST_READ answered from the table, PARAM_SET sent to the owning
service(s) and the value in force echoed to every ground station (as PX4 does). Unknown names are
answered as PX4 answers them (params.py), refusals explained in a STATUSTEXT.
"""
from __future__ import annotations

from typing import Any, Callable

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import ParamSetReply
from aeroperception.services.runtime import CallError

from .ops import StackOps
from .params import ParamTable, decode_param_id, decode_value


class ParamProtocol:
    """own: this service's name and its parameters (own_params() -> ParamList, set_own(name,
    value) -> ParamSetReply), answered without a call; ops reaches the others. send(msg,
    broadcast=...) to ground stations, notify(text, peer, severity) a STATUSTEXT, ignored(kind)
    counts an input dropped."""

    def __init__(self, table: ParamTable, ops: StackOps, own: str, own_params: Callable[[], Any],
                 set_own: Callable[[str, Any], ParamSetReply], send: Callable[..., None],
                 notify: Callable[..., None], ignored: Callable[[str], None], log: Any):
        self.table, self.ops = table, ops
        self.own, self.own_params, self.set_own = own, own_params, set_own
        self.send, self.notify, self.ignored, self.log = send, notify, ignored, log

    def refresh(self) -> None:
        """Every source service's declared parameters, again (a service not running keeps what we had)."""
        for svc in self.table.sources:
            if svc == self.own:
                self.table.update_service(svc, self.own_params().params)
                continue

            def done(res, svc=svc) -> None:
                if not isinstance(res, CallError):
                    self.table.update_service(svc, res.params)

            self.ops.list_params(svc, done)

    def on_request_list(self, msg, now_s: float) -> None:
        for i, e in enumerate(self.table.entries):
            self.send(self.table.value_msg(i, e))

    def on_request_read(self, msg, now_s: float) -> None:
        """PARAM_REQUEST_READ; an unknown name gets no PARAM_VALUE (PX4), only PARAM_ERROR."""
        name = decode_param_id(msg.param_id)
        found = self.table.lookup(name, msg.param_index)
        if found is not None:
            self.send(self.table.value_msg(*found))
            return
        self.ignored("unknown_param")
        if msg.param_index >= 0:
            self.notify(f"[pm] unknown param ID: {msg.param_index}", _peer(msg), M.MAV_SEVERITY_INFO)
        self._error(msg, name, M.MAV_PARAM_ERROR_DOES_NOT_EXIST)

    def _error(self, msg, name: str, error: int) -> None:
        self.send(M.MAVLink_param_error_message(msg.get_srcSystem(), msg.get_srcComponent(), name.encode()[:16],
                                                getattr(msg, "param_index", -1), error))

    def on_set(self, msg, now_s: float) -> None:
        """PARAM_SET: to the owning service(s) (an alias: every owner present), then the value in
        force to every ground station (as PX4 does); refusals explained in a STATUSTEXT."""
        name = decode_param_id(msg.param_id)
        peer = _peer(msg)
        found = self.table.lookup(name)
        if found is None:
            self.ignored("unknown_param")
            self.notify(f"[pm] unknown param: {name}", peer, M.MAV_SEVERITY_INFO)
            self._error(msg, name, M.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            return
        index, entry = found
        if entry.readonly:
            self.notify(f"{name} is read-only: {entry.readonly}", peer, M.MAV_SEVERITY_WARNING)
            self._error(msg, name, M.MAV_PARAM_ERROR_READ_ONLY)
            self.send(self.table.value_msg(index, entry))
            return
        try:
            value = decode_value(msg.param_value, msg.param_type, entry.ptype)
        except Exception:  # noqa: BLE001 - an undecodable value: echo the current one
            self.send(self.table.value_msg(index, entry))
            return
        targets = entry.targets or ((entry.service, entry.name),)
        replies: dict[tuple[str, str], ParamSetReply] = {}

        def record(target: tuple[str, str], reply: ParamSetReply) -> None:
            replies[target] = reply
            if len(replies) < len(targets):
                return
            for (svc, pname), rep in replies.items():
                if rep.success and rep.value is not None:
                    self.table.set_value(svc, pname, rep.value)
                elif not rep.success:
                    self.log.warn("param_set_rejected", param=name, service=svc, name=pname, value=value,
                                  error=rep.message)
                    if entry.targets:
                        self.notify(f"{name}: {svc} refused {value}: {rep.message}", peer, M.MAV_SEVERITY_WARNING)
            now = self.table.lookup(name)
            if now is not None:   # always echoed, to every ground station (as PX4 does): the value in force
                self.send(self.table.value_msg(*now), broadcast=True)

        for svc, pname in targets:
            if svc == self.own:
                record((svc, pname), self.set_own(pname, value))
            else:
                self.ops.set_param(svc, pname, value, lambda reply, target=(svc, pname): record(target, reply))


def _peer(msg) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()
