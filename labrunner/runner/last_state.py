"""How the last session left the lab, as far as the store knows: the mount, the chamber, its setpoint.

`resume` reads it twice. The sequencer asks whether the campaign was ever mounted (a campaign
that never was gets its first remount prompt whatever the IMU measures) and which run the IMU is
in, to go on in the same run when it resumes in place. A resumed dry run starts its simulated lab
in this state: the IMU still mounted as it was, powered since that mount, the chamber air at its
last stored reading and heading for the last setpoint the sequencer gave (the remount temperature
after a safe stop, a remount or the park before fitting).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass

import numpy as np
from sqlalchemy import and_, or_, select

from labrunner.store import Store, events, sample_blocks

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LastMount:
    """The latest remount the sequencer recorded: what it mounted, the run it began, when (campaign time)."""

    orientation: str
    run: int
    t_s: float


@dataclass(frozen=True)
class LeftState:
    mount: LastMount | None  # None: never mounted
    chamber_c: float | None  # the latest stored chamber reading
    imu_temp_c: float | None  # the latest stored IMU temperature
    setpoint_c: float | None  # the latest setpoint the sequencer gave (None: none yet, the chamber idles)


def last_mount(store: Store, campaign_id: int) -> LastMount | None:
    """The latest 'IMU mounted ...' event of a campaign (None: it was never mounted)."""
    ev = events.c
    q = (select(ev.t_s, ev.detail).where(ev.campaign_id == campaign_id, ev.kind == "operator",
                                         ev.message.like("IMU mounted %"))
         .order_by(ev.id.desc()).limit(1))
    with store.reading() as conn:
        row = conn.execute(q).first()
    if row is None:
        return None
    try:
        detail = json.loads(row.detail or "{}")
        return LastMount(orientation=str(detail["orientation"]), run=int(detail["run"]), t_s=float(row.t_s))
    except (ValueError, KeyError, TypeError) as exc:  # an event written by an older version, or damaged
        log.warning("campaign %d: the last mount event has no readable orientation/run (%s)", campaign_id, exc)
        return None


def last_setpoint(store: Store, campaign_id: int, remount_c: float) -> float | None:
    """The setpoint the sequencer last gave the chamber: a step's ('setpoint X C'), or the remount
    temperature (on the way to a remount, in the safe stop, parked before fitting)."""
    ev = events.c
    q = (select(ev.message, ev.detail).where(
        ev.campaign_id == campaign_id,
        or_(and_(ev.kind == "info", or_(ev.message.like("setpoint %"), ev.message.like("lab in safe state%"))),
            and_(ev.kind == "transition", or_(ev.message.like("% -> mounting"), ev.message.like("% -> fitting")))))
         .order_by(ev.id.desc()).limit(1))
    with store.reading() as conn:
        row = conn.execute(q).first()
    if row is None:
        return None
    if str(row.message).startswith("setpoint "):
        try:
            return float(json.loads(row.detail or "{}")["setpoint_c"])
        except (ValueError, KeyError, TypeError):
            return None
    return remount_c


def last_readings(store: Store, campaign_id: int) -> tuple[float | None, float | None]:
    """The chamber reading and the IMU temperature stored last (with a record or a monitor stretch)."""
    sb = sample_blocks.c
    q = (select(sb.chamber, sb.encoding, sb.temp_lsb, sb.temp_c).where(sb.campaign_id == campaign_id)
         .order_by(sb.t0_s.desc(), sb.id.desc()).limit(1))
    with store.reading() as conn:
        row = conn.execute(q).first()
    if row is None:
        return None, None
    pairs = np.frombuffer(row.chamber, dtype="<f8").reshape(-1, 2)
    chamber = float(pairs[np.argmax(pairs[:, 0]), 1]) if pairs.size else None
    temps = (np.frombuffer(row.temp_c, dtype="<i2") * float(row.temp_lsb) if row.encoding == "i16"
             else np.frombuffer(row.temp_c, dtype="<f4").astype(float))
    finite = temps[np.isfinite(temps)]
    return chamber, float(finite[-1]) if finite.size else None


def left_state(store: Store, campaign_id: int, remount_c: float) -> LeftState:
    chamber, imu = last_readings(store, campaign_id)
    return LeftState(mount=last_mount(store, campaign_id), chamber_c=chamber, imu_temp_c=imu,
                     setpoint_c=last_setpoint(store, campaign_id, remount_c))


__all__ = ["LastMount", "LeftState", "last_mount", "last_readings", "last_setpoint", "left_state"]
