"""``python -m sssphase_daemon``: run the acquisition daemon in the foreground (systemd, ``sss daemon start``)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from pathlib import Path

from sssphase_daemon import protocol, security


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="sssphase_daemon", description=__doc__)
    parser.add_argument("--endpoint", help="control endpoint (default: ipc:// socket in the runtime dir)")
    parser.add_argument("--preview", help="optional PUB endpoint for a live preview that may drop frames")
    parser.add_argument("--curve-dir", type=Path, help="CURVE keys from `sss daemon keys` (required off loopback)")
    parser.add_argument("--client-timeout", type=float, default=10.0, help="seconds without heartbeat before a client counts as dead")
    parser.add_argument("--max-message-bytes", type=int, default=protocol.DEFAULT_MAX_MESSAGE_BYTES)
    parser.add_argument("--state-file", type=Path, help="where to write endpoint, pid and token (default: runtime dir)")
    parser.add_argument("--exit-when-idle", type=float, metavar="SECONDS",
                        help="exit once no rig is open, no job runs and no client was heard from for this long")
    args = parser.parse_args(argv)
    if args.exit_when_idle is not None and not args.exit_when_idle > 0:  # NaN too
        parser.error(f"--exit-when-idle must be a positive number of seconds, got {args.exit_when_idle}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    import zmq

    from sssphase_daemon.server import Daemon, limit_malloc_arenas

    limit_malloc_arenas()  # before the daemon's threads start
    try:
        daemon = Daemon(args.endpoint, curve_dir=args.curve_dir, preview=args.preview,
                        client_timeout_s=args.client_timeout, max_message_bytes=args.max_message_bytes,
                        state_file=args.state_file or security.state_path(), exit_when_idle_s=args.exit_when_idle)
    except zmq.ZMQError as exc:  # a bind that failed: address in use, no such interface, ...
        print(f"sssphase daemon: cannot listen: {exc}", file=sys.stderr)
        return 2
    except (PermissionError, OSError, ValueError) as exc:  # (InputError is a ValueError: SSS_OPEN_TIMEOUT_S=abc)
        print(f"sssphase daemon: {exc}", file=sys.stderr)
        return 2

    def stop(signum: int, frame: object) -> None:
        daemon.running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    path = daemon.write_state()
    logging.getLogger("sssphase.daemon").info("serving on %s (state in %s)", daemon.endpoint, path)
    daemon.serve_forever()
    import threading

    native = ("sss-discover", "sss-device-", "sss-close-")  # threads that may be inside a driver's native code
    if any(t.is_alive() and t.name.startswith(native) for t in threading.enumerate()):  # one still is (it hangs):
        logging.shutdown()  # the interpreter's teardown would crash under it (SIGSEGV, abort)
        os._exit(0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
