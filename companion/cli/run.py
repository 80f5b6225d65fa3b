"""``companion run [--config FILE]``: start the positioning daemon (``companion.daemon``)."""
from __future__ import annotations

import logging
import signal
import sys

from companion.daemon.config import ConfigError, default_config_path, load_config
from companion.daemon.service import Daemon, setup_logging

log = logging.getLogger("companion")


def configure_parser(parser) -> None:
    parser.add_argument("--config", metavar="FILE", default=None,
                        help=f"YAML config (default: the embedded {default_config_path().name}: bundled replay, "
                             "maps/warehouse.yaml, udpout:127.0.0.1:14550)")


def main(args) -> int:
    setup_logging()
    try:
        config = load_config(args.config)
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
