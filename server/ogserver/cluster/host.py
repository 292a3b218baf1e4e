"""``ClusterHost``: the ``SessionHost`` of a front-end whose sessions live in named, detached Ray actors.

Creating a session reserves its place in the cluster's ``Directory`` (limits cluster-wide), starts a
``SessionActor`` named after the session id with the configured resource request (Ray places it on
a node that has them) and opens the session inside it. Any front-end finds any session by that name,
so a client may stream through one front-end and render through another. A front-end holds no map
and keeps nothing a session needs: stopping it leaves every session running in the cluster.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import grpc
import ray
from ogapi.v1 import mapping_pb2 as pb
from ray import ObjectRef
from ray.actor import ActorHandle
from ray.exceptions import GetTimeoutError, RayActorError
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from ogserver.api import validation
from ogserver.cluster.actor import SessionActor
from ogserver.cluster.connect import join
from ogserver.cluster.directory import Directory
from ogserver.cluster.remote import ACK_GROUP, RemoteSession, call, outcome
from ogserver.errors import ServiceError
from ogserver.sessions.counters import FrameTotals
from ogserver.sessions.hosting import Closed, HostedSession, Opened, Upload
from ogserver.sessions.registry import check_label, new_session_id, requested_config
from ogserver.settings import Settings

log = logging.getLogger(__name__)
NAMESPACE = "ogmapping"
DIRECTORY_NAME = "directory"
# A session actor that no node can take (its CPUs/GPUs are all requested) stays pending; after this
# long the CreateSession is refused instead of waiting for a node to join or a session to close.
PLACEMENT_SECONDS = 120.0
ACTOR_CONCURRENCY = 16  # a blocked frame offer, the ack poll, renders, stats and snapshots side by side
MAX_RESTARTS = 3  # Ray restarts a session's actor (on any node) this often after its process or node died
# The directory lives on the head node, beside Ray's own control store (GCS): a lost worker node never takes it.
HEAD_NODE = {"node:__internal_head__": 0.001}


def actor_name(session_id: str) -> str:
    return f"session-{session_id}"


def session_alive(session_id: str) -> bool:
    """Whether the session's actor still exists (running, or being restarted by Ray); Ray releases the name of
    an actor that is dead for good (its restarts spent, or killed without restart)."""
    try:
        ray.get_actor(actor_name(session_id), namespace=NAMESPACE)
    except ValueError:
        return False
    return True


class ClusterHost:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.record_dir = Path(settings.record_dir)
        join(settings.cluster, settings.cluster_connect_seconds,
             lambda: ray.init(address=settings.cluster, namespace=NAMESPACE, log_to_driver=False))
        self.device = f"ray cluster {settings.cluster}"
        self._directory = ray.remote(Directory).options(
            name=DIRECTORY_NAME, namespace=NAMESPACE, lifetime="detached", get_if_exists=True, num_cpus=0,
            resources=HEAD_NODE,
        ).remote(session_alive)
        self._actor = ray.remote(concurrency_groups={ACK_GROUP: 1})(SessionActor)
        log.info("cluster mode: sessions are Ray actors in namespace %r of %s (%g CPUs, %g GPUs each)", NAMESPACE,
                 settings.cluster, settings.session_cpus, settings.session_gpus)

    def check_label(self, label: str) -> None:
        check_label(label, self.settings)

    def create(self, request: pb.CreateSessionRequest, owner: str) -> Opened:
        requested_config(request, self.settings)  # refuse a bad request before an actor is started for it
        return self._place(owner, lambda actor, session_id: actor.open.remote(request.SerializeToString(), owner,
                                                                              session_id))

    def restore(self, owner: str, receive: Callable[[], Upload]) -> Opened:
        """The place is reserved before ``receive`` reads the snapshot: a full cluster refuses at once."""
        return self._place(owner, lambda actor, session_id: actor.restore.remote(owner, receive(), session_id))

    def _place(self, owner: str, opening: Callable[[ActorHandle, str], ObjectRef]) -> Opened:
        limits = self.settings.limits.max_sessions, self.settings.access.max_sessions_per_client
        call(self._directory, "reserve", owner, *limits)
        session_id = new_session_id()
        committed = False
        try:
            actor = self._actor.options(
                name=actor_name(session_id), namespace=NAMESPACE, lifetime="detached",
                num_cpus=self.settings.session_cpus, num_gpus=self.settings.session_gpus,
                max_concurrency=ACTOR_CONCURRENCY, max_restarts=MAX_RESTARTS,
                scheduling_strategy=self._placement(session_id),
            ).remote(self.settings, session_id, self._directory)
            try:
                config, token, recording = self._opened(actor, opening(actor, session_id))
            except BaseException:
                ray.kill(actor)
                raise
            call(self._directory, "commit", owner, session_id)
            committed = True
        finally:
            if not committed:
                call(self._directory, "release", owner, session_id)
        log.info("session %s opened for %s in a Ray actor on node %s", session_id, owner, call(actor, "node_id"))
        return Opened(RemoteSession(actor, config, recording), token)

    def _placement(self, session_id: str) -> NodeAffinitySchedulingStrategy | str:
        """The emptiest live node with the resources a session asks for, softly: if it is full or gone, Ray
        places the actor elsewhere, and restarts it elsewhere when that node dies. Ray's own choice (DEFAULT)
        when no node can take it now (one may join within PLACEMENT_SECONDS)."""
        wanted = {"CPU": self.settings.session_cpus, "GPU": self.settings.session_gpus}
        candidates = [node["NodeID"] for node in ray.nodes() if node["Alive"] and all(
            node["Resources"].get(resource, 0.0) >= amount for resource, amount in wanted.items() if amount > 0)]
        if not candidates:
            return "DEFAULT"
        return NodeAffinitySchedulingStrategy(call(self._directory, "place", session_id, candidates), soft=True)

    def _opened(self, actor: ActorHandle, pending: ObjectRef) -> tuple[pb.SessionConfig, str, Path]:
        try:
            ray.get(actor.__ray_ready__.remote(), timeout=PLACEMENT_SECONDS)
        except GetTimeoutError:
            raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                               f"no node of the cluster could take the session within {PLACEMENT_SECONDS:g} s "
                               f"({self.settings.session_cpus:g} CPUs, {self.settings.session_gpus:g} GPUs)") from None
        except RayActorError:
            pass  # its start failed: the opening call says why
        config, token, recording = outcome(pending, "open")
        return pb.SessionConfig.FromString(config), token, Path(recording)

    def _actor_of(self, session_id: str, field: str) -> ActorHandle:
        try:
            return ray.get_actor(actor_name(session_id), namespace=NAMESPACE)
        except ValueError:
            raise ServiceError(grpc.StatusCode.NOT_FOUND, f"{field}: no session {session_id}") from None

    @staticmethod
    def _remote(actor: ActorHandle, described: tuple[bytes, str]) -> RemoteSession:
        config, recording = described
        return RemoteSession(actor, pb.SessionConfig.FromString(config), Path(recording))

    def get(self, session_id: str, token: str, field: str = "session_id") -> HostedSession:
        session_id = validation.session_id(session_id, field)
        actor = self._actor_of(session_id, field)
        return self._remote(actor, call(actor, "authorize", token))

    def touch(self, session: HostedSession) -> None:
        assert isinstance(session, RemoteSession)
        call(session.actor, "touch")

    def sessions(self, owner: str | None = None) -> list[HostedSession]:
        found: list[HostedSession] = []
        for session_id in call(self._directory, "sessions", owner):
            try:
                actor = self._actor_of(session_id, "session_id")
                found.append(self._remote(actor, call(actor, "describe")))
            except ServiceError as error:  # closed meanwhile, or its node is gone: listed once it is back
                log.info("session %s not listed: %s", session_id, error.message)
        return found

    def frame_totals(self) -> FrameTotals:
        """Frames of the sessions open in the cluster now (closed ones are no longer counted in cluster mode)."""
        totals = FrameTotals()
        for session in self.sessions():
            totals += FrameTotals.of(session.counters())
        return totals

    def _forget(self, session: RemoteSession) -> None:
        call(self._directory, "drop", session.id)
        ray.kill(session.actor)

    def close(self, session: HostedSession) -> Closed:
        assert isinstance(session, RemoteSession)
        closed = call(session.actor, "close")
        self._forget(session)
        return closed

    def expire_idle(self) -> list[Closed]:
        """Each idle session closes itself in its actor (its registry's own expiry); its actor then goes."""
        expired = []
        for session in self.sessions():
            assert isinstance(session, RemoteSession)
            try:
                closed = call(session.actor, "expire_idle")
            except ServiceError:  # closed by another front-end meanwhile, or unavailable
                continue
            if closed:
                self._forget(session)
                expired.extend(closed)
        return expired

    def close_all(self, timeout: float) -> list[Closed]:
        """A front-end stopping closes nothing: its sessions stay in the cluster for the other front-ends."""
        ray.shutdown()
        return []
