"""Rigid transforms over time: one interpolated track per TF edge or pose topic, and the TF tree.

A ``Track`` holds the pose of a child frame in its parent at sorted stamps and answers for any
stamp between two samples by linear interpolation of the translation and slerp of the rotation,
as tf2 does; outside its samples it answers only within ``tolerance`` of the end sample (tf2 does
not extrapolate at all). A static track (``/tf_static``) answers at any stamp. ``TransformTree``
composes the edges between two frames, through their nearest common ancestor, into the pose of
one frame in the other.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ogmapping.frames.rotation import quaternion_pose, slerp


def invert(transform: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    inverse[:3, :3] = transform[:3, :3].T
    inverse[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return inverse


class Track:
    """Poses of ``child`` in ``parent`` over time (stamps in nanoseconds), sorted once when first asked."""

    def __init__(self, parent: str, child: str, static: bool = False) -> None:
        self.parent, self.child, self.static = parent, child, static
        self._samples: list[tuple[int, tuple[float, ...], tuple[float, ...]]] = []
        self._stamps: np.ndarray | None = None
        self._translations: np.ndarray | None = None
        self._rotations: np.ndarray | None = None

    def add(self, stamp_ns: int, translation: tuple[float, ...], quaternion: tuple[float, ...]) -> None:
        if self.static:  # a later static transform replaces an earlier one, as in tf2
            self._samples.clear()
        self._samples.append((stamp_ns, translation, quaternion))
        self._stamps = None

    def __len__(self) -> int:
        return len(self._samples)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._stamps is None:
            samples = sorted(self._samples, key=lambda s: s[0])
            self._stamps = np.array([s[0] for s in samples], dtype=np.int64)
            self._translations = np.array([s[1] for s in samples], dtype=np.float64).reshape(-1, 3)
            rotations = np.array([s[2] for s in samples], dtype=np.float64).reshape(-1, 4)
            norms = np.linalg.norm(rotations, axis=1, keepdims=True)
            if not (np.isfinite(rotations).all() and (norms > 1e-9).all() and np.isfinite(self._translations).all()):
                raise ValueError(f"transform {self.parent} -> {self.child} has a non-finite or zero quaternion")
            self._rotations = rotations / norms
        assert self._translations is not None and self._rotations is not None
        return self._stamps, self._translations, self._rotations

    def at(self, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """Pose of the child in the parent at ``stamp_ns``, or None where the track does not reach."""
        stamps, translations, rotations = self._arrays()
        if len(stamps) == 0:
            return None
        if self.static:
            return quaternion_pose(translations[-1], rotations[-1])
        right = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if right < len(stamps) and stamps[right] == stamp_ns:
            return quaternion_pose(translations[right], rotations[right])
        if right == 0 or right == len(stamps):
            end = 0 if right == 0 else len(stamps) - 1
            if abs(int(stamps[end]) - stamp_ns) > tolerance_ns:
                return None
            return quaternion_pose(translations[end], rotations[end])
        left = right - 1
        alpha = (stamp_ns - int(stamps[left])) / (int(stamps[right]) - int(stamps[left]))
        translation = translations[left] + alpha * (translations[right] - translations[left])
        return quaternion_pose(translation, slerp(rotations[left], rotations[right], alpha))


class TransformTree:
    """The TF tree of a bag: one track per (parent, child) edge, each child with one parent."""

    def __init__(self) -> None:
        self.tracks: dict[str, Track] = {}  # by child frame
        self._children: defaultdict[str, set[str]] = defaultdict(set)

    def add(self, parent: str, child: str, stamp_ns: int, translation: tuple[float, ...],
            quaternion: tuple[float, ...], static: bool) -> None:
        track = self.tracks.get(child)
        if track is None:
            track = self.tracks[child] = Track(parent, child, static)
            self._children[parent].add(child)
        elif track.parent != parent:
            raise ValueError(f"TF frame {child!r} has two parents, {track.parent!r} and {parent!r}")
        elif track.static != static:
            raise ValueError(f"TF edge {parent} -> {child} is published both on /tf and on /tf_static")
        track.add(stamp_ns, translation, quaternion)

    @property
    def frames(self) -> set[str]:
        return set(self.tracks) | set(self._children)

    def ancestors(self, frame: str) -> list[str]:
        """``frame``, its parent, its parent's parent, ... up to the root."""
        chain = [frame]
        while chain[-1] in self.tracks:
            chain.append(self.tracks[chain[-1]].parent)
            if len(chain) > len(self.tracks) + 1:
                raise ValueError(f"TF has a loop through {frame!r}")
        return chain

    def root(self, frame: str) -> str:
        return self.ancestors(frame)[-1]

    def edges_between(self, fixed: str, frame: str) -> tuple[list[Track], list[Track]] | None:
        """Tracks from the common ancestor down to ``fixed`` and down to ``frame``; None if unconnected."""
        up_fixed, up_frame = self.ancestors(fixed), self.ancestors(frame)
        common = next((f for f in up_fixed if f in set(up_frame)), None)
        if common is None:
            return None
        to_fixed = [self.tracks[f] for f in up_fixed[: up_fixed.index(common)]]
        to_frame = [self.tracks[f] for f in up_frame[: up_frame.index(common)]]
        return to_fixed, to_frame

    def connected(self, fixed: str, frame: str) -> bool:
        return self.edges_between(fixed, frame) is not None

    def moves(self, fixed: str, frame: str) -> bool:
        """Whether any edge between the two frames changes over time (else TF only mounts the camera)."""
        edges = self.edges_between(fixed, frame)
        return edges is not None and any(not track.static for track in edges[0] + edges[1])

    def lookup(self, fixed: str, frame: str, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """Pose of ``frame`` in ``fixed`` at the stamp, or None where an edge has no transform then."""
        edges = self.edges_between(fixed, frame)
        if edges is None:
            return None
        poses = []
        for chain in edges:
            pose = np.eye(4)
            for track in chain:  # child-most first: compose from the common ancestor downwards
                step = track.at(stamp_ns, tolerance_ns)
                if step is None:
                    return None
                pose = step @ pose
            poses.append(pose)
        common_to_fixed, common_to_frame = poses
        return invert(common_to_fixed) @ common_to_frame
