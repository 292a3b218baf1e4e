"""The cluster's one list of sessions, their owners and nodes: max_sessions and the per-caller quota,
cluster-wide, and where a new session goes.

A named, detached Ray actor that runs one call at a time, so two front-ends creating sessions at once
cannot both take the last place, nor both pick the same emptiest node. It holds ids, owners and node
ids only; the sessions are their own actors, which report the node they run on whenever they start
(again). A new session goes to the node holding the fewest sessions, so a lost node takes as few as
possible. A
session whose actor is dead for good (Ray's restarts spent, its node gone for good) never closes
through a front-end: when the cluster is full, such sessions are dropped before a place is refused.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from ogserver.errors import ServiceError
from ogserver.sessions.limits import check_room

log = logging.getLogger(__name__)


class Directory:
    def __init__(self, alive: Callable[[str], bool]) -> None:
        self._alive = alive  # whether a session's actor still exists, given the session id
        self._owners: dict[str, str] = {}  # session id -> the caller that created it
        self._reserved: Counter[str] = Counter()  # places held while a session actor is being started
        self._nodes: dict[str, str] = {}  # session id -> the Ray node id it runs on (or was sent to)

    def reserve(self, owner: str, limit: int, quota: int) -> None:
        try:
            self._check_room(owner, limit, quota)
        except ServiceError:
            if not self.prune():
                raise
            self._check_room(owner, limit, quota)
        self._reserved[owner] += 1

    def _check_room(self, owner: str, limit: int, quota: int) -> None:
        held = self._reserved[owner] + sum(holder == owner for holder in self._owners.values())
        check_room(len(self._owners) + self._reserved.total(), held, owner, limit, quota, "cluster")

    def prune(self) -> list[str]:
        """Drop the sessions whose actor is dead for good; their ids."""
        dead = [session_id for session_id in self._owners if not self._alive(session_id)]
        for session_id in dead:
            self._nodes.pop(session_id, None)
            log.warning("session %s of %s dropped: its actor is dead for good (its recording and checkpoint stay "
                        "on the shared storage)", session_id, self._owners.pop(session_id))
        return dead

    def place(self, session_id: str, candidates: list[str]) -> str:
        """The node of ``candidates`` (those that can take the session) holding the fewest sessions, first
        listed on a tie; held for ``session_id`` until its actor reports where it runs."""
        load = Counter(self._nodes.values())
        node = min(candidates, key=lambda candidate: load[candidate])
        self._nodes[session_id] = node
        return node

    def placed(self, session_id: str, node: str) -> None:
        """A session's actor started (again, after a failure) on ``node``."""
        self._nodes[session_id] = node

    def commit(self, owner: str, session_id: str) -> None:
        self._reserved[owner] -= 1
        self._owners[session_id] = owner

    def release(self, owner: str, session_id: str) -> None:
        self._reserved[owner] -= 1
        self._nodes.pop(session_id, None)

    def drop(self, session_id: str) -> None:
        self._owners.pop(session_id, None)
        self._nodes.pop(session_id, None)

    def sessions(self, owner: str | None) -> list[str]:
        return [session_id for session_id, holder in self._owners.items() if owner is None or holder == owner]
