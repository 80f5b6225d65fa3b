"""``companion run [--config FILE] [--replay PATH] [--log-level LEVEL]``: start the positioning daemon
(``companion.daemon``)."""
from __future__ import annotations

import logging
import signal
import sys

from companion.daemon.config import ConfigError, default_config_path, load_config
from companion.daemon.service import LOG_LEVELS, Daemon, setup_logging

log = logging.getLogger("companion")


def configure_parser(parser) -> None:
    parser.add_argument("--config", metavar="FILE", default=None,
                        help=f"YAML config (default: the embedded {default_config_path().name}: bundled replay, "
                             "maps/warehouse.yaml, udpout:127.0.0.1:14550)")
    parser.add_argument("--replay", metavar="PATH", default=None,
                        help="replay this sequence folder, video or image folder in real time instead of the "
                             "config's source (the rest of the config as it is)")
    parser.add_argument("--log-level", choices=LOG_LEVELS, default="info",
                        help="least important messages logged (default info; debug adds every skipped frame "
                             "and retry)")


def main(args) -> int:
    setup_logging(args.log_level)
    try:
        config = load_config(args.config, replay=args.replay)
        daemon = Daemon(config, status_stream=sys.stdout)
    except (ConfigError, ValueError) as error:
        log.error("%s", error)
        return 2
    previous = {sig: signal.signal(sig, lambda signum, _frame: _on_signal(daemon, signum))
                for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        return daemon.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _on_signal(daemon: Daemon, signum: int) -> None:
    log.info("%s: stopping", signal.Signals(signum).name)
    daemon.stop_event.set()
