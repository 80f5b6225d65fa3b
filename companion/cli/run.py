"""``companion run [--config FILE] [--replay PATH [--fps FPS]] [--loop] [--log-level LEVEL] [--record DIR] [--http HOST:PORT]``:
start the positioning daemon (``companion.daemon``)."""
from __future__ import annotations

import dataclasses
import logging
import signal
import sys
from pathlib import Path

from companion.daemon.config import (Config, ConfigError, ReplayConfig, V4L2Config, default_config_path,
                                     http_address, load_config)
from companion.daemon.record import RecordError, RecordParams
from companion.daemon.web import WebError
from companion.yaml_input import Where
from companion.daemon.service import LOG_LEVELS, Daemon, setup_logging
from companion.cli import discard_stdout, start_signals

log = logging.getLogger("companion")


def configure_parser(parser) -> None:
    parser.add_argument("--config", metavar="FILE", default=None,
                        help=f"YAML config (default: the embedded {default_config_path().name}: bundled replay, "
                             "maps/warehouse.yaml, udpout:127.0.0.1:14550)")
    parser.add_argument("--replay", metavar="PATH", default=None,
                        help="replay this sequence folder, video or image folder in real time instead of the "
                             "config's source (the rest of the config as it is)")
    parser.add_argument("--fps", type=float, default=None,
                        help="frame rate of a --replay image folder without timestamps.csv, or of a video "
                             "instead of the rate it states")
    parser.add_argument("--loop", action="store_true",
                        help="replay the recording over and over (a replay's source.loop), until stopped")
    parser.add_argument("--log-level", choices=LOG_LEVELS, default="info",
                        help="least important messages logged (default info; debug adds every skipped frame "
                             "and retry)")
    parser.add_argument("--record", metavar="DIR", default=None,
                        help="record the flight into the sequence folder DIR (new or empty; '{time}' in it becomes "
                             "the start time), replayable with source: {kind: replay, path: DIR}; the config's "
                             "record section sets codec and limits")
    parser.add_argument("--http", metavar="HOST:PORT", default=None,
                        help="serve the live view there (like status.http; e.g. 127.0.0.1:8080)")


def main(args) -> int:
    setup_logging(args.log_level)
    if _stopped_while_starting():
        return 0
    try:
        config = with_options(load_config(args.config, replay=args.replay, replay_fps=args.fps), args)
        daemon = Daemon(config, status_stream=sys.stdout)
    except RecordError as error:   # the folder named by the key or option that gave it
        log.error("%s: %s", "--record" if args.record is not None else f"{config.path}: record.path", error.problem)
        return 2
    except WebError as error:      # the address, the same way
        log.error("%s: %s", "--http" if args.http is not None else f"{config.path}: status.http", error.problem)
        return 2
    except (ConfigError, ValueError) as error:
        log.error("%s", error)
        return 2
    previous = {sig: signal.signal(sig, lambda signum, _frame: _on_signal(daemon, signum))
                for sig in (signal.SIGTERM, signal.SIGINT)}
    previous[signal.SIGHUP] = signal.signal(signal.SIGHUP, lambda _signum, _frame: _on_hangup())
    if _stopped_while_starting():  # while the config loaded: it starts and stops at once, in order
        daemon.stop_event.set()
    try:
        return daemon.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if daemon.status_stream is None:  # stdout failed and was given up
            discard_stdout()


def with_options(config: Config, args) -> Config:
    """The config with ``--loop``, ``--record`` and ``--http`` applied over its ``source.loop``, ``record`` and
    ``status.http``."""
    if args.loop:
        if not isinstance(config.source, ReplayConfig):
            camera = "a V4L2 camera" if isinstance(config.source, V4L2Config) else "a simulated camera"
            raise ConfigError(f"--loop replays a recording over and over: the source of {config.path} is {camera}, "
                              "not a replay (give --replay PATH)")
        config = dataclasses.replace(config, source=dataclasses.replace(config.source, loop=True))
    if args.record is not None:
        record = config.record or RecordParams(path=Path(args.record))
        config = dataclasses.replace(config, record=dataclasses.replace(record, path=Path(args.record)))
    if args.http is not None:
        config = dataclasses.replace(config, http=http_address(args.http, Where("command line (--http)", ConfigError, "status")))
    return config


def _stopped_while_starting() -> bool:
    """The signals that came while `companion run` started (``cli.start_signals``: its modules importing, its
    config loading), said now that the log is set up: True after a SIGTERM (a systemd stop: exit 0); a SIGHUP
    is said as later and changes nothing."""
    stopped = False
    while start_signals:
        signum = start_signals.pop(0)
        if signum == signal.SIGHUP:
            _on_hangup()
        elif not stopped:
            log.info("%s while starting: stopping", signal.Signals(signum).name)
            stopped = True
    return stopped


def _on_hangup() -> None:
    """SIGHUP: the terminal that started the daemon went away (an ssh session dropped as the vehicle flew
    out of Wi-Fi range). The vehicle's positioning must not end with it: the daemon goes on."""
    log.warning("SIGHUP (the terminal went away?): the daemon goes on; SIGTERM or SIGINT stops it")


def _on_signal(daemon: Daemon, signum: int) -> None:
    if not daemon.stop_event.is_set():   # a second one while stopping says nothing new
        log.info("%s: stopping", signal.Signals(signum).name)
    daemon.stop_event.set()
