"""Whether the daemon's session has a router, for a daemon that is a client of routers.

zenoh drops what a session puts while no router is connected (it reconnects by itself and
sends again from then on). The daemon still records every message; :class:`RouterLink`
lets it count those it recorded while no router could take them (``messages_unrouted``
in its stop summary, docs/deployment.md). A thread asks the session for its routers every
``period_s``: a message within one period of a change may be counted on either side.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)


class RouterLink:
    """``up``: the session had at least one router at the last look; ``changes``: how
    often that flipped (each logged)."""

    def __init__(
        self,
        session: zenoh.Session,
        period_s: float = 0.01,
        said: tuple[str, str] = (
            "no router: recording goes on, messages counted as unrouted",
            "router reached again: publishing resumes",
        ),
    ) -> None:
        self._session = session
        self._said = said  # the lines logged when the router is lost, and when reached
        self._period_s = period_s
        self.up = self._look()
        self.changes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="router-link", daemon=True)
        self._thread.start()

    def _look(self) -> bool:
        try:
            return any(True for _ in self._session.info.routers_zid())
        except Exception:  # the session is closing
            return False

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            up = self._look()
            if up != self.up:
                self.changes += 1
                log.warning(self._said[1] if up else self._said[0])
                self.up = up

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
