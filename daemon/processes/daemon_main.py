"""`roadlog run` (the car's daemon, live drivers) and `roadlog replay` (the same daemon fed by a log player).

Each first takes the bus's and the data folder's locks (`instance_lock`): a second daemon on either is refused."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from daemon.bus.pubsub import open_publisher, unlink_all
from daemon.bus.ring_space import check_rings
from daemon.log_format.reader import not_a_log
from daemon.processes.instance_lock import EXIT_ALREADY_RUNNING, AlreadyRunning, hold_instance_locks
from daemon.processes.supervisor import Supervisor
from daemon.spine.config import ConfigError, data_dir, load_config, reports_config_errors
from daemon.spine.process_logging import LEVELS, LOG_LEVEL_ENV, setup_logging
from daemon.spine.process_table import playback_rate, process_table
from daemon.spine.stop_signals import on_signals
from daemon.spine.topics import topic_table

REPLAY_OUTPUT_DIR = "roadlog-output"  # a replay's logs and map without --output-dir: in the current directory
log = logging.getLogger(__name__)


def create_rings(config) -> None:
    """Make every topic's ring afresh before any process starts (rings left by a crashed run are removed
    first: their messages are in the recovered segments), so consumers can subscribe, and register as
    lossless readers, before their producers exist (the rings were checked before: `_serve`)."""
    unlink_all(config)
    for name in topic_table(config):
        try:
            open_publisher(config, name).close()
        except RuntimeError:  # a live writer from an earlier run still holds it: it exists
            pass


def _serve(supervisor: Supervisor, config, data_folder: Path) -> int:
    def stop(signum: int) -> None:  # in the signal relay's thread (daemon.spine.stop_signals)
        log.info("signal %s, shutting down", signal.Signals(signum).name)
        supervisor.stop_event.set()

    check_rings(config)  # rings that cannot work (too small for their messages, beyond /dev/shm): ConfigError
    try:  # before anything touches the rings or the segments: they may be another daemon's
        locks = hold_instance_locks(config, data_folder)
    except AlreadyRunning as exc:
        print(exc, file=sys.stderr, flush=True)
        return EXIT_ALREADY_RUNNING
    supervisor.inherit_fds = locks.fds  # held until the last of its children is gone too
    on_signals(stop)
    create_rings(config)
    try:
        code = supervisor.run()
    finally:
        unlink_all(config)
    locks.release()  # its children are gone (if run() raised, they hold the locks until they die with it)
    return code


def _add_log_level(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-level", choices=LEVELS, default=None,
                        help=f"the daemon's and its processes' log level (default: ${LOG_LEVEL_ENV}, else info)")


def _supervisor(config, table, args, **options) -> Supervisor:
    """The supervisor of this run, logging at --log-level and passing it to every process it starts."""
    setup_logging("supervisor", args.log_level)
    env = {LOG_LEVEL_ENV: args.log_level} if args.log_level else {}
    return Supervisor(config, table, env=env, **options)


@reports_config_errors
def run_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog run", description="Run the daemon on the car's live sensors.")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--output-dir", help="log and map folder (default: recorder.output_dir)")
    parser.add_argument("--no-record", action="store_true", help="do not record logs")
    _add_log_level(parser)
    args = parser.parse_args(argv)
    config = load_config(args.config)
    table = process_table(config, args.config, "live", record=not args.no_record, output_dir=args.output_dir)
    return _serve(_supervisor(config, table, args), config, data_dir(config, args.output_dir))


@reports_config_errors
def replay_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog replay",
                                     description="Run the daemon with the drivers replaced by a log player.")
    parser.add_argument("logs", nargs="+", help="MCAP segments to play")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--rate", default="1.0", help="playback speed factor, or 'max' (lossless, as fast as "
                                                     "the mapper takes it)")
    parser.add_argument("--output-dir", default=REPLAY_OUTPUT_DIR,
                        help=f"log and map folder (default: ./{REPLAY_OUTPUT_DIR}, in the current directory)")
    parser.add_argument("--no-record", action="store_true", help="do not record the replayed messages again")
    _add_log_level(parser)
    args = parser.parse_args(argv)
    try:
        playback_rate(args.rate)  # the player would refuse it, after the daemon started (and recorded) for nothing
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    config = load_config(args.config)
    unusable = [why for why in map(not_a_log, args.logs) if why]
    if unusable:  # before any process starts: the player would refuse them, or play nothing, with the others up
        raise ConfigError("; ".join(unusable))
    table = process_table(config, args.config, "replay", replay_logs=tuple(args.logs), replay_rate=args.rate,
                          record=not args.no_record, output_dir=args.output_dir)
    return _serve(_supervisor(config, table, args, exit_when_done=True), config,
                  data_dir(config, args.output_dir))
