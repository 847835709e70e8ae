"""``eqa export``: an episode's record in a format other tools read.

    eqa export EPISODE_ID --mcap [-o FILE]   the episode as MCAP (ROS 2 messages + EQA events; docs/mcap.md)

Reads the episode's stored events from the store (``EQA_REDIS_URL``, or the embedded store under
``EQA_DATA_DIR``) and its recording from ``{EQA_DATA_DIR}/recordings/`` when it was recorded.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_export(args: argparse.Namespace) -> int:
    from eqa import keys
    from eqa.store import open_store, unavailable_errors
    from eqa_app.cli import UsageError, load_settings
    from gateway import mcap_export, recordings
    from gateway.manager import ev_key

    if not args.mcap:
        raise UsageError("say which format: --mcap (the only one so far)")
    try:
        eid = keys.check_id(args.episode_id, "episode id")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    settings = load_settings()
    out = Path(args.output) if args.output else Path(f"{eid}.mcap")
    if not out.parent.is_dir():
        raise UsageError(f"the folder of {out} does not exist")
    store = open_store(settings)
    try:
        events = mcap_export.read_events(lambda e, after, n: store.read(ev_key(e), after=after, count=n), eid)
    except unavailable_errors() as exc:
        raise UsageError(f"cannot read the store ({exc}); check EQA_REDIS_URL / EQA_DATA_DIR") from None
    finally:
        store.close()
    try:
        summary = mcap_export.export_episode(settings, eid, events, out)
    except FileNotFoundError:
        raise UsageError(f"no episode {eid!r} in the store or under {settings.recordings_path} "
                         "(EQA_REDIS_URL / EQA_DATA_DIR point at the fleet's?)") from None
    except recordings.RecordingError as exc:
        raise UsageError(str(exc)) from None
    print(f"{summary.path}: {summary.total} messages on {len(summary.messages)} channels")
    for topic, n in sorted(summary.messages.items()):
        print(f"  {topic:32s} {summary.schemas[topic]:32s} {n}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("export", help="write an episode as MCAP (Foxglove, ros2 bag, Rerun)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("episode_id", help="the episode, ep-...")
    p.add_argument("--mcap", action="store_true", help="write MCAP (ROS 2 messages and EQA JSON events)")
    p.add_argument("-o", "--output", default=None, help="output file (default ./EPISODE_ID.mcap)")
    p.set_defaults(func=cmd_export)
