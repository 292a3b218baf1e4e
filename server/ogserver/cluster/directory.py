"""The cluster's one list of sessions and their owners: max_sessions and the per-caller quota, cluster-wide.

A named, detached Ray actor that runs one call at a time, so two front-ends creating sessions at once
cannot both take the last place. It holds ids and owners only; the sessions are their own actors.
"""

from __future__ import annotations

from collections import Counter

from ogserver.places import check_room


class Directory:
    def __init__(self) -> None:
        self._owners: dict[str, str] = {}  # session id -> the caller that created it
        self._reserved: Counter[str] = Counter()  # places held while a session actor is being started

    def reserve(self, owner: str, limit: int, quota: int) -> None:
        held = self._reserved[owner] + sum(holder == owner for holder in self._owners.values())
        check_room(len(self._owners) + self._reserved.total(), held, owner, limit, quota, "cluster")
        self._reserved[owner] += 1

    def commit(self, owner: str, session_id: str) -> None:
        self._reserved[owner] -= 1
        self._owners[session_id] = owner

    def release(self, owner: str) -> None:
        self._reserved[owner] -= 1

    def drop(self, session_id: str) -> None:
        self._owners.pop(session_id, None)

    def sessions(self, owner: str | None) -> list[str]:
        return [session_id for session_id, holder in self._owners.items() if owner is None or holder == owner]
