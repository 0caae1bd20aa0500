"""What every worker process of the server runs first: it ends when the server does.

The planner's and the body decoder's pools are ``spawn``-ed children of the server. A server that
shuts down stops them; one killed with SIGKILL cannot, and they lived on under PID 1 (about 255
MB) beside the next server. :func:`start` watches the parent from a daemon thread and ends the
worker within :data:`WATCH_S` of the parent's death, however it died.
"""

from __future__ import annotations

import os
import threading
import time

#: How often a worker looks whether its server is still there (seconds).
WATCH_S = 0.5


def start(niceness: int = 0) -> None:
    """A pool's initializer: lower the worker's CPU priority by ``niceness`` (the planners yield
    to the server's own threads), free memory back to the system when arrays are freed, and end
    the worker when its parent is gone."""
    from service.intake.memory import return_freed_memory

    if niceness:
        os.nice(niceness)
    return_freed_memory()
    parent = os.getppid()
    threading.Thread(target=_watch, args=(parent,), daemon=True, name="watch-parent").start()


def _watch(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(WATCH_S)
    os._exit(0)  # the server died: nothing is waiting for this worker's results
