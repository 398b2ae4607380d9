"""The campaign lease: one writer per campaign, across processes and hosts.

The lease lives in the campaign's row (`Store.take_lease`: a token, the holder's pid and host, the
wall time of its last renewal). A `run` holds it from the moment it creates the campaign, a `resume`
takes it before it builds or connects to any instrument, the heartbeat (`runner.control`, every
`HEARTBEAT_S` = 2 s of wall time) and every sample write renew it, and the session releases it at the
end. This module decides whether a lease someone holds may be taken.

The rules:

- a free lease (nobody holds it, or the holder released it) is taken;
- a holder on this host whose process is gone (kill -9, power loss) is stale at once: taken, and said so;
- a holder whose last heartbeat is older than `STALE_AFTER_S` (60 s of wall time, thirty missed
  heartbeats) is taken only when asked to (`resume --take-over`): its process may be hung, or alive
  on a host that lost the database;
- anything else is refused, naming the holder (host, pid, age of its last heartbeat).
"""

from __future__ import annotations

import logging
import os
import time
import uuid
from dataclasses import dataclass

from labrunner.errors import UserError
from labrunner.store import LeaseHolder, Store

log = logging.getLogger(__name__)

# Wall seconds without a heartbeat after which a lease counts as stale (the heartbeat renews it every
# 2 s; a record step's commit renews it too). Documented in README and docs/design.md.
STALE_AFTER_S = 60.0


class LeaseRefused(UserError):
    """Another process holds the campaign's lease; the message names it and what would take it."""


def new_token() -> str:
    """A token naming one session's hold on a lease (a pid can be reused; a token is not)."""
    return uuid.uuid4().hex


def pid_alive(pid: int | None) -> bool:
    """Whether a process of this host with that pid exists."""
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, as another user
        return True
    return True


def holder_alive(pid: int | None, host: str | None, heartbeat_wall: float | None, now: float | None = None) -> bool:
    """Whether the holder of a lease is to be taken as running: on this host its process exists; on
    another host (where its process cannot be seen) its heartbeat is younger than `STALE_AFTER_S`."""
    if host == os.uname().nodename:
        return pid_alive(pid)
    if heartbeat_wall is None:
        return False
    return (time.time() if now is None else now) - heartbeat_wall <= STALE_AFTER_S


def describe(holder: LeaseHolder, now: float) -> str:
    """'pid 4242 on lab-pc, last heartbeat 12 s ago'."""
    age = "no heartbeat" if holder.heartbeat_wall is None else (
        f"last heartbeat {max(0.0, now - holder.heartbeat_wall):.0f} s ago")
    return f"pid {holder.pid} on {holder.host or '?'}, {age}"


@dataclass(frozen=True)
class LeaseDecision:
    """Why a lease was taken: "free", "gone" (same-host process dead) or "taken over" (stale, asked)."""

    reason: str
    previous: str | None  # the holder it replaced, described


class LeaseRules:
    """`decide` for `Store.take_lease`: raises `LeaseRefused`, or records why the lease may be taken."""

    def __init__(self, db: object, take_over: bool) -> None:
        self.db = db
        self.take_over = take_over
        self.decision: LeaseDecision | None = None

    def __call__(self, holder: LeaseHolder) -> None:
        now = time.time()
        cid = holder.campaign_id
        if holder.token is None:
            self.decision = LeaseDecision("free", None)
            return
        who = describe(holder, now)
        here = os.uname().nodename
        if holder.host == here and not pid_alive(holder.pid):
            self.decision = LeaseDecision("gone", who)
            return
        age = None if holder.heartbeat_wall is None else now - holder.heartbeat_wall
        stale = age is None or age > STALE_AFTER_S
        if stale and self.take_over:
            self.decision = LeaseDecision("taken over", who)
            return
        if stale:
            raise LeaseRefused(
                f"{self.db}: campaign {cid} is held by {who}, stale (no heartbeat for more than "
                f"{STALE_AFTER_S:.0f} s): make sure that process is stopped, then labrunner resume {self.db} "
                "--take-over")
        raise LeaseRefused(
            f"{self.db}: campaign {cid} is running: held by {who}; only one process may run a campaign "
            f"(a lease without a heartbeat for {STALE_AFTER_S:.0f} s can be taken with resume --take-over); "
            "use labrunner status or abort")


def acquire(store: Store, campaign_id: int, *, take_over: bool = False) -> LeaseDecision:
    """Take the campaign's lease for this process or raise `LeaseRefused` naming the holder."""
    rules = LeaseRules(store.path, take_over)
    store.take_lease(campaign_id, new_token(), rules)
    assert rules.decision is not None
    if rules.decision.previous is not None:
        log.warning("campaign %d: lease %s from %s", campaign_id,
                    "taken over" if rules.decision.reason == "taken over" else "taken (process gone)",
                    rules.decision.previous)
    return rules.decision


__all__ = ["STALE_AFTER_S", "LeaseDecision", "LeaseRefused", "acquire", "holder_alive", "new_token", "pid_alive"]
