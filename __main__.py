"""``python -m polarstripe``: the command line (tools/cli.py). A Ctrl-C that comes while a command is still
being imported or parsed (a node just started by the launcher) ends it with status 130 and no traceback;
from then on the command handles it (docs/architecture.md "Shutdown").

A node process (``polarstripe node``) leaves without the interpreter's teardown: by then its loop has
ended, ``teardown`` has run, its sockets are closed and its files removed, and unloading numba, scipy and
matplotlib can take seconds on a loaded machine, while the launcher's next signal is on its way. Its last
half second (the sockets' linger) ignores the stop signals: one that came then raised a traceback.

From its first line a node process writes every thread's Python stack to its log on SIGUSR1 (``faulthandler``:
it works while the interpreter is stuck in C code holding the GIL). The launcher sends it to a node still
running after its SIGINT, before the SIGTERM, so the log says where the node was stuck."""

import faulthandler
import os
import signal
import sys

NODE = sys.argv[1:2] == ["node"]
if NODE:
    faulthandler.register(signal.SIGUSR1, all_threads=True)

try:
    from polarstripe.tools.cli import main

    status = main()
except KeyboardInterrupt:
    status = 130
if NODE:
    # the node has ended: a stop signal from now on (the launcher's next one) has nothing left to stop and
    # must not raise KeyboardInterrupt into the teardown below (a traceback); SIGKILL still ends it
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    import logging
    import threading

    import zmq

    # what the closed sockets still queue (the last heartbeat, "exiting") gets at most 0.25 s to leave:
    # os._exit skips the context's termination, which is what waits for a socket's linger
    ender = threading.Thread(target=zmq.Context.instance().destroy, kwargs={"linger": 250}, daemon=True)
    ender.start()
    ender.join(0.5)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status if isinstance(status, int) else 1)
raise SystemExit(status)
