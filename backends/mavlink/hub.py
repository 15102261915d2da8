"""One MAVLink router and one I/O thread per gateway, shared by the MAVLink source and backend.

``run --source mavlink:EP --mavlink EP…`` must route the vehicle's traffic to the ground
stations and theirs back, as mavlink-router does, in the same process as the translation.  So
the source (the vehicle side: its endpoints, and the listener node that reads the vehicle)
and the backend (the ground-station side: its endpoints, and the rocket node) do not each run
a router: whichever starts first creates the gateway's :class:`MavlinkHub` in the gateway's
:class:`~gateway.backend.GatewayContext`, the other joins it, and the last to leave closes it.
A source or backend built on its own (a test, another program) gets a hub of its own.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

from backends.mavlink.endpoints import Endpoint, EndpointSpec, make_endpoint
from backends.mavlink.router import LocalNode, Router
from gateway.backend import GatewayContext
from gateway.io.ioloop import IoLoop
from gateway.io.server import ClientLimits

log = logging.getLogger(__name__)

SERVICE = "mavlink.hub"
GCS = "gcs"  # the backend's endpoints: ground stations
VEHICLE = "vehicle"  # the source's endpoints: the vehicle


class MavlinkHub:
    """A router, the loop its endpoints run on, and who uses them."""

    def __init__(self, name: str = "mavlink") -> None:
        self.name = name
        self.router = Router()
        self.loop = IoLoop(name)
        self.router.use_loop(self.loop)
        self._users = 0
        self._lock = threading.Lock()
        self._started = False
        self.groups: set[str] = set()
        #: the vehicle names of this gateway's sources that hear several systems and name one
        #: vehicle per system (the MAVLink source): not vehicles of their own (no node)
        self.stems: set[str] = set()

    @classmethod
    def of(cls, context: GatewayContext) -> MavlinkHub:
        """The gateway's hub (created on first use)."""
        with _create_lock:
            hub = context.services.get(SERVICE)
            if hub is None or hub.closed:
                hub = context.services[SERVICE] = cls()
            return hub

    @property
    def closed(self) -> bool:
        return self._started and self._users == 0

    def expect(self, group: str) -> None:
        """Announce, before anything starts, that a node will serve ``group`` (the source
        does, at attach time, so the rocket knows from its first tick that it shares the
        router with a vehicle)."""
        with self._lock:
            self.groups.add(group)

    def join(self, node: LocalNode | None, group: str, *, step: int = 1,
             forward: bool | None = None, signing_key: bytes | None = None) -> None:
        """Serve ``node`` (None: none yet, see :meth:`add`); its own messages go to links of
        ``group``.  ValueError for a signing key that differs from another user's (then
        nothing is joined)."""
        router = self.router
        with self._lock:
            if signing_key is not None:
                router.set_signing_key(signing_key)
            if forward is not None:
                router.forward = forward
            if not self._started:
                self.loop.start()
                self._started = True
            self._users += 1
            self.groups.add(group)
        if node is not None:
            router.add_node(node, (group,), step=step)

    def add(self, node: LocalNode, group: str) -> None:
        """Serve another node of a user that has joined (its messages to ``group``'s links);
        it stops with :meth:`remove` or with the user's :meth:`leave`."""
        self.router.add_node(node, (group,))

    def remove(self, node: LocalNode) -> None:
        self.router.remove_node(node)

    def open(self, specs: Sequence[EndpointSpec], group: str, queue_depth: int,
             limits: ClientLimits | None = None) -> list[Endpoint]:
        """Open ``specs`` as links of ``group`` on the hub's loop; OSError naming the first
        that cannot be opened (those opened before it are closed again)."""
        started: list[Endpoint] = []
        try:
            for spec in specs:
                ep = make_endpoint(spec, queue_depth, group=group, limits=limits)
                started.append(ep)
                ep.start(self.loop, self.router)
        except OSError:
            for ep in started:
                ep.close()
            raise
        return started

    def side(self, group: str) -> tuple[bool, bool]:
        """Whether a node serves ``group`` (e.g. a vehicle side is routed here), and whether
        a system has been heard on one of its links."""
        with self.router.lock:
            present = group in self.groups
            heard = present and any(link.seen for link in self.router.links
                                    if link.group == group)
        return present, heard

    def leave(self, node: LocalNode | None, endpoints: Sequence[Endpoint] = (),
              timeout: float = 0.5) -> None:
        """Close ``endpoints`` (queued frames are written first) and stop serving ``node``;
        the last user stops the loop."""
        each = max(0.05, timeout / (2 * max(1, len(endpoints))))
        for ep in endpoints:
            try:
                ep.close(each)
            except Exception:
                log.debug("%s: closing %s failed", self.name, ep.name, exc_info=True)
        if node is not None:
            self.router.remove_node(node)
        self.groups = set(self.router.node_groups())
        with self._lock:
            self._users -= 1
            last = self._users == 0
        if last and self.loop.stop(max(0.05, timeout / 2)):
            self.loop.close()


_create_lock = threading.Lock()
