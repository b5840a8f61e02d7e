"""What a fault row is (`Row`: inject, observe, expected outcome) and the observations rows share:
a restarted service, the mission's states, progress along the mission, fmu's first hold, holding after
an outage. Times are monotonic seconds in this process; the capture holds what the stack published."""
from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.tools.harness import Capture, SimStack, poll_until, speed

from .judging import flying_on_mps


@dataclass
class Ctx:
    """What a row's inject/observe steps share: the stack, a capture of its keys, the injection time."""

    st: SimStack
    rec: Capture
    t_inject: float = 0.0
    notes: dict = field(default_factory=dict)


@dataclass
class Row:
    name: str
    injected: str
    expected: str
    inject: Callable[[Ctx], None]
    observe: Callable[[Ctx], tuple[bool, str, float | None]]   # passed, observed, detect/react s
    airborne: bool = True          # inject mid-mission (else on the ground)
    cleanup: Callable[[Ctx], None] = lambda c: None
    breaks_stack: bool = False     # restart the stack afterwards
    prepare: Callable[[Ctx], None] = lambda c: None
    sensors: str = "none"          # the sim's --sensors this row needs (the stack restarts to change it)


def kill(ctx: Ctx, name: str) -> None:
    pid = ctx.st.pid(name)
    if pid is None:
        raise RuntimeError(f"no running {name} process in pids.json")
    ctx.notes["old_pid"] = pid
    os.kill(pid, signal.SIGKILL)


def restarted(ctx: Ctx, name: str, timeout_s: float = 20.0) -> float | None:
    """Seconds from the kill until a new `name` process holds the liveliness token, else None."""
    old = ctx.notes["old_pid"]
    ok = poll_until(lambda: ctx.st.pid(name) not in (None, old) and ctx.st.alive(name, timeout_s=0.5), timeout_s, 0.1)
    return time.monotonic() - ctx.t_inject if ok else None


def mission_states(ctx: Ctx, since: float) -> list[str]:
    seq = [m.state for _, m in ctx.rec.since("status", since)]
    return [s for i, s in enumerate(seq) if i == 0 or s != seq[i - 1]]


def progressing(ctx: Ctx, window_s: float = 3.0) -> bool:
    """The mission is flying its waypoints: EXECUTING and the truth moving."""
    t0 = time.monotonic()
    time.sleep(window_s)
    truth = ctx.rec.since("truth", t0)
    st = ctx.rec.last("status")
    if st is None or st.state != "EXECUTING" or len(truth) < 2:
        return False
    return float(np.linalg.norm(truth[-1][1].position_m.to_array() - truth[0][1].position_m.to_array())) > 1.0


def flies_on(ctx: Ctx, window_s: float = 3.0) -> bool:
    """The mission goes on: flying its waypoints (`progressing`), or already landing or landed."""
    return progressing(ctx, window_s) or ctx.rec.last("status").state in ("LAND", "IDLE")


def first_hold(ctx: Ctx, since: float) -> float | None:
    """Seconds from `since` to the first zero-velocity setpoint fmu sent: its brake (velocity
    only) or its position hold — fmu brakes to a stop first, then holds where it stopped."""
    with ctx.st.tap.lock:
        sps = [(t, m) for t, m in ctx.st.tap.setpoints if t >= since]
    for t, m in sps:
        if not m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE and m.vx == m.vy == m.vz == 0.0:
            return t - since
    return None


def held_after(ctx: Ctx, settle_s: float = 6.0, window_s: float = 2.0) -> tuple[bool, str]:
    """After an outage the mission must have held (HOLDING or LAND among its states since the
    injection) and the vehicle must not fly on in OFFBOARD while the mission says HOLDING.
    Ending EXECUTING again is allowed once it held: a resume by policy after the re-check."""
    time.sleep(settle_s)
    t_obs = time.monotonic()
    time.sleep(window_s)
    status = ctx.rec.last("status")
    truth = ctx.rec.since("truth", t_obs)
    moving = any(m.flight_mode == "OFFBOARD" and speed(m) > flying_on_mps(ctx.st.profile) for _, m in truth)
    states = mission_states(ctx, ctx.t_inject)
    reacted = any(s in ("HOLDING", "LAND") for s in states)
    ok = status is not None and reacted and not (status.state == "HOLDING" and moving)
    fc_modes = sorted({m.flight_mode for _, m in ctx.rec.since("truth", ctx.t_inject)})
    return ok, (f"FC modes {','.join(fc_modes)}; mission {'->'.join(states)}; "
                f"{'moving in OFFBOARD' if moving else 'not flying on'} {settle_s + window_s:.0f} s after")


def pause(name: str, seconds: float):
    def inject(ctx: Ctx) -> None:
        pid = ctx.st.pid(name)
        if pid is None:
            raise RuntimeError(f"no running {name} process")
        ctx.notes["paused_pid"] = pid
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            os.kill(pid, signal.SIGCONT)
        ctx.notes["resumed"] = time.monotonic()
    return inject


def resume(ctx: Ctx) -> None:
    pid = ctx.notes.get("paused_pid")
    if pid:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
