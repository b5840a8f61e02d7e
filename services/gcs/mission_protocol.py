"""The mission protocol state machine (upload, download, clear, set current) for mission_type 0,
without Zenoh."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from pymavlink.dialects.v20 import common as M

from .messages import MissionAck, MissionCount, statustext
from .mission_items import Item, plan_id

@dataclass
class Transfer:
    direction: str              # "upload" (GCS -> us) or "download" (us -> GCS)
    peer: tuple[int, int]       # (system, component) of the ground station
    count: int
    mission_type: int = 0
    items: list[Item | None] = field(default_factory=list)
    expected: int = 0
    last_send_s: float = 0.0
    retries: int = 0
    use_int: bool = True        # upload: MISSION_REQUEST_INT vs legacy MISSION_REQUEST


LoadFn = Callable[[list[Item], Callable[[bool, str, int], None]], None]


class MissionProtocol:
    """The mission micro-service (mission_type 0; fence/rally answered as empty).

    send(msg): transmit one MAVLink message object.
    load(items, done): hand a complete upload to the stack; done(ok, message, mav_result) may be
        called later (from another thread, under the same lock as the rest of the service).
    notify(text, peer): tell one ground station why its upload was refused (STATUSTEXT); by
        default the STATUSTEXT goes through send().

    One upload at a time: while one ground station uploads, another one's MISSION_COUNT,
    MISSION_REQUEST_LIST or MISSION_CLEAR_ALL is refused (MISSION_ACK DENIED, counted as "busy");
    the same ground station may restart its own upload.
    """

    def __init__(self, send: Callable, load: LoadFn, item_timeout_s: float = 0.25, retries: int = 5,
                 max_items: int = 500, log: Callable[..., None] | None = None,
                 notify: Callable[[str, tuple[int, int]], None] | None = None):
        self.send = send
        self.load = load
        self.notify = notify or (lambda text, peer: [self.send(m) for m in statustext(M.MAV_SEVERITY_CRITICAL, text)])
        self.item_timeout_s = item_timeout_s
        self.retries = retries
        self.max_items = max_items
        self.log = log or (lambda *a, **k: None)
        self.items = []                      # the accepted mission, as uploaded (sets plan_id)
        self.current = 0
        self.transfer: Transfer | None = None
        self.loading = False
        self.errors: dict[str, int] = {}
        self.uploads_accepted = 0
        self.uploads_rejected = 0

    @property
    def items(self) -> list[Item]:
        return self._items

    @items.setter
    def items(self, items: list[Item]) -> None:
        self._items = list(items)
        self.plan_id = plan_id(self._items)   # MISSION_CURRENT.mission_id, MISSION_ACK/COUNT opaque_id

    def _err(self, what: str) -> None:
        self.errors[what] = self.errors.get(what, 0) + 1

    def _ack(self, peer, result: int, mission_type: int = 0) -> None:
        opaque = self.plan_id if result == M.MAV_MISSION_ACCEPTED and mission_type == M.MAV_MISSION_TYPE_MISSION else 0
        self.send(MissionAck(peer[0], peer[1], result, mission_type, opaque))

    def _busy(self, peer, loading: bool = True) -> bool:
        """Another ground station's upload is under way (or, with `loading`, an upload is being
        loaded into the stack)."""
        t = self.transfer
        return (t is not None and t.direction == "upload" and t.peer != peer) or (loading and self.loading)

    # ------------------------------------------------------------ upload (GCS -> us)

    def on_count(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if self._busy(peer):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        if mtype != M.MAV_MISSION_TYPE_MISSION:
            # No fences or rally points here: an empty list is fine, anything else is unsupported.
            self._ack(peer, M.MAV_MISSION_ACCEPTED if msg.count == 0 else M.MAV_MISSION_UNSUPPORTED, mtype)
            return
        if msg.count > self.max_items:
            self._err("count_too_large")
            self.transfer = None
            self.notify(f"Mission rejected: {msg.count} items, at most {self.max_items}", peer)
            self._ack(peer, M.MAV_MISSION_NO_SPACE, mtype)
            return
        if msg.count == 0:
            self.transfer = None
            self.clear(peer)
            return
        self.transfer = Transfer("upload", peer, msg.count, mtype, [None] * msg.count, 0)
        self._request(now_s)

    def _request(self, now_s: float) -> None:
        t = self.transfer
        assert t is not None
        if t.use_int:
            self.send(M.MAVLink_mission_request_int_message(t.peer[0], t.peer[1], t.expected, t.mission_type))
        else:
            self.send(M.MAVLink_mission_request_message(t.peer[0], t.peer[1], t.expected, t.mission_type))
        t.last_send_s = now_s

    def on_item(self, msg, now_s: float) -> None:
        t = self.transfer
        if t is None or t.direction != "upload":
            self._err("item_without_upload")
            return
        if (msg.get_srcSystem(), msg.get_srcComponent()) != t.peer:
            self._err("item_from_other_peer")   # not part of the upload under way
            return
        if getattr(msg, "mission_type", 0) != t.mission_type:
            self._err("item_wrong_type")
            return
        if msg.seq != t.expected:
            # Out of order (or a duplicate): ask again for the one we need (only the
            # expected seq is accepted).
            self._err("item_out_of_order")
            if msg.seq > t.expected:
                self._request(now_s)
            return
        if msg.get_type() == "MISSION_ITEM":
            t.use_int = False
        t.items[t.expected] = Item.from_msg(msg)
        t.expected += 1
        t.retries = 0
        if t.expected < t.count:
            self._request(now_s)
            return
        items = [it for it in t.items if it is not None]
        self.transfer = None
        self.loading = True
        peer, mtype = t.peer, t.mission_type

        def done(ok: bool, message: str, result: int) -> None:
            self.loading = False
            if ok:
                self.items = items
                self.current = 0
                self.uploads_accepted += 1
                self._ack(peer, M.MAV_MISSION_ACCEPTED, mtype)
            else:
                self.uploads_rejected += 1
                self.log("mission_rejected", message=message)
                self.notify(f"Mission rejected: {message}", peer)   # before the ACK: shown with it
                self._ack(peer, result if result != M.MAV_MISSION_ACCEPTED else M.MAV_MISSION_ERROR, mtype)

        self.load(items, done)

    # ------------------------------------------------------------ download (us -> GCS)

    def on_request_list(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype != M.MAV_MISSION_TYPE_MISSION:
            self.send(MissionCount(peer[0], peer[1], 0, mtype))
            return
        if self._busy(peer, loading=False):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        n = len(self.items)
        self.send(MissionCount(peer[0], peer[1], n, mtype, self.plan_id))
        self.transfer = Transfer("download", peer, n, mtype, list(self.items), 0, now_s) if n else None

    def on_request(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype != M.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self.items):
            self._err("request_out_of_range")
            self._ack(peer, M.MAV_MISSION_INVALID_SEQUENCE, mtype)
            return
        it = self.items[msg.seq]
        it.current = 1 if msg.seq == self.current else 0
        if msg.get_type() == "MISSION_REQUEST_INT":
            self.send(it.to_msg_int(peer[0], peer[1], mtype))
        else:
            self.send(it.to_msg_legacy(peer[0], peer[1], mtype))
        if self.transfer is not None and self.transfer.direction == "download":
            self.transfer.last_send_s = now_s

    def on_ack(self, msg, now_s: float) -> None:
        if self.transfer is not None and (msg.get_srcSystem(), msg.get_srcComponent()) != self.transfer.peer:
            return   # another ground station's ACK says nothing about this transfer
        if self.transfer is not None and self.transfer.direction == "download":
            self.transfer = None
        elif self.transfer is not None and self.transfer.direction == "upload" and msg.type != M.MAV_MISSION_ACCEPTED:
            self.transfer = None  # the ground station cancelled its upload

    # ------------------------------------------------------------ clear / current

    def clear(self, peer, mission_type: int = 0) -> None:
        self.items = []
        self.current = 0
        self._ack(peer, M.MAV_MISSION_ACCEPTED, mission_type)

    def on_clear_all(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype not in (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_ALL):
            self._ack(peer, M.MAV_MISSION_ACCEPTED, mtype)
            return
        if self._busy(peer):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        self.transfer = None
        self.clear(peer, mtype)

    def set_current(self, seq: int) -> bool:
        if not 0 <= seq < len(self.items):
            self._err("set_current_out_of_range")
            return False
        self.current = seq
        return True

    # ------------------------------------------------------------ timers

    def tick(self, now_s: float) -> None:
        t = self.transfer
        if t is None:
            return
        if t.direction == "upload":
            if now_s - t.last_send_s < self.item_timeout_s:
                return
            if t.retries >= self.retries:
                self._err("upload_timeout")
                self.transfer = None
                self._ack(t.peer, M.MAV_MISSION_OPERATION_CANCELLED, t.mission_type)
                return
            t.retries += 1
            self._request(now_s)
        elif now_s - t.last_send_s > max(5.0, self.item_timeout_s * self.retries * 4):
            self.transfer = None  # the ground station stopped asking; forget the download

    def handlers(self) -> dict[str, Callable]:
        """{MAVLink message type: handler(msg, now_s)} for every mission-protocol message."""
        return {
            "MISSION_COUNT": self.on_count, "MISSION_ITEM_INT": self.on_item, "MISSION_ITEM": self.on_item,
            "MISSION_REQUEST_LIST": self.on_request_list, "MISSION_REQUEST_INT": self.on_request,
            "MISSION_REQUEST": self.on_request, "MISSION_ACK": self.on_ack,
            "MISSION_CLEAR_ALL": self.on_clear_all,
        }

    def handle(self, msg, now_s: float) -> bool:
        """Dispatch one mission-protocol message; False if it is not one."""
        fn = self.handlers().get(msg.get_type())
        if fn is None:
            return False
        fn(msg, now_s)
        return True
