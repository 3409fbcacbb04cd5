"""``davis-info``: what a session.h5 (or a .davisreplay) holds, as text or JSON.

Thin front end over :func:`davis_rig.session.info.describe_session` and
:func:`davis_rig.usb.replay_info.describe_replay`; the file's first bytes say which one applies. Every file is
described on its own: one that cannot be read gets one ``davis-info: error: ...`` line (exit 4) and the others
are still printed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from davis_rig.cli.common import EXIT_OK, error_message, exit_code_for, new_parser, run_main
from davis_rig.errors import DavisRigError

NAME = "davis-info"

EXAMPLES = """\
examples:
  davis-info recordings/sample.h5                  # duration, rates, losses, device, labels, integrity
  davis-info recordings/sample.h5 --json           # the same as one JSON object (a list for several files)
  davis-info recordings/sample.davisreplay         # a raw USB replay: the camera, transfers, decoded counts

Integrity: "complete" (closed cleanly), "recording" (a davis-record is writing it now), "needs recovery" (a
journal is next to it: davis-record --recover rebuilds the recording), "incomplete" (not closed cleanly, no
journal). Times are device µs."""

#: First bytes of the file kinds davis-info recognises.
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
ZIP_SIGNATURE = b"PK\x03\x04"


def build_parser():
    """Return the argument parser of ``davis-info``."""
    parser = new_parser(NAME, "Summarise session.h5 recordings (and .davisreplay files).", EXAMPLES)
    parser.add_argument("files", nargs="+", metavar="FILE", help="session.h5 or .davisreplay files")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    return parser


def _not_a_session(path: Path, head: bytes) -> str | None:
    """Why ``path`` is another kind of file davis-info does not describe, or ``None``."""
    from davis_rig.session.aedat4 import AEDAT4_MAGIC

    if head.startswith(AEDAT4_MAGIC):
        return ("an AEDAT4 recording (iniVation DV), not a session: import it with "
                "`python tools/aedat4_to_session.py IN.aedat4 OUT.h5`, then run davis-info on OUT.h5")
    if head.startswith(b"% "):
        return ("a Prophesee .dat event file (text header), not a session: import it with "
                "davis_rig.session.prophesee.import_prophesee_dat")
    if head.startswith(ZIP_SIGNATURE):
        return "a zip / numpy .npz file, not a session: import a davis-export npz with davis_rig.session.npz.import_npz"
    return None


def describe(path: Path):
    """Describe one file: ``("session", SessionInfo)`` or ``("replay", ReplayInfo)``.

    Raises:
        FormatError: the file is missing, damaged, or another kind of file (the message says what it is).
    """
    from davis_rig.errors import FormatError
    from davis_rig.usb.replay import REPLAY_MAGIC

    head = b""
    if path.is_file():
        with open(path, "rb") as file:
            head = file.read(16)
    elif path.exists():
        raise FormatError(f"{path}: not a file")
    if head.startswith(REPLAY_MAGIC):
        from davis_rig.usb.replay_info import describe_replay

        return "replay", describe_replay(path)
    if head and not head.startswith(HDF5_SIGNATURE):
        from davis_rig.session.journal import journal_path

        reason = _not_a_session(path, head)
        if reason is None:
            journal = journal_path(path)
            reason = (f"not a session.h5: not an HDF5 file (it starts with {head[:8]!r})"
                      + (f"; {journal.name} exists next to it: run `davis-record --recover {path}`"
                         if journal.exists() else ""))
        raise FormatError(f"{path}: {reason}")
    from davis_rig.session.info import describe_session

    return "session", describe_session(path)


# --- text -------------------------------------------------------------------------------------
def _size(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{n / 2**10:.1f} KiB"


def _rate(hz: float) -> str:
    for scale, unit in ((1e6, "M"), (1e3, "k")):
        if hz >= scale:
            return f"{hz / scale:.2f} {unit}"
    return f"{hz:.1f} "


def _items(mapping: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in mapping.items()) if mapping else "none"


def _span(t_first, t_last, duration_us: int) -> str:
    if t_first is None:
        return "no events"
    return f"{duration_us / 1e6:.3f} s (events {t_first} … {t_last} µs, device clock)"


def _session_text(info) -> list[str]:
    from davis_rig.session.info import PEAK_WINDOW_MS

    lines = [f"{info.path}: davis_rig session (format {info.format_version}, written by davis_rig "
             f"{info.toolkit_version or '?'}), {_size(info.file_size_bytes)}",
             f"  integrity     {info.integrity}: {info.integrity_detail}",
             f"  recorded      {info.recording_start_utc or 'unknown start'}",
             f"  duration      {_span(info.t_first_event_us, info.t_last_event_us, info.duration_us)}",
             f"  events        {info.events:,}  mean {_rate(info.event_rate_mean_hz)}ev/s, peak "
             f"{_rate(info.event_rate_peak_hz)}ev/s ({PEAK_WINDOW_MS} ms window)"]
    exposure = f", exposure {info.exposure_median_us:.0f} µs (median)" if info.exposure_median_us is not None else ""
    lines.append(f"  APS frames    {info.frames:,}  {info.frame_rate_hz:.1f} fps{exposure}")
    lines.append(f"  IMU samples   {info.imu_samples:,}" + (f"  {info.imu_rate_hz:.1f} Hz" if info.imu_samples else ""))
    lines.append(f"  specials      {info.specials:,}  {_items(info.specials_by_type)}")
    usb = ("not recorded" if info.dropped_transfers is None
           else f"{info.dropped_transfers} transfers ({info.dropped_bytes or 0} bytes)")
    lines.append(f"  drops         USB {usb}; decoder {_items(info.decoder_losses)}; events back in time "
                 f"{info.events_dropped_non_monotonic}; timestamp resets {info.timestamp_resets}")
    device = info.device_info
    version = f"{device.get('logic_version', '?')}.{device.get('logic_patch', 0)}"
    extra = "".join(f", {key}" for key in ("synthetic",) if device.get(key))
    source = f", imported from {device['imported_from']}" if device.get("imported_from") else ""
    lines.append(f"  device        serial {info.serial or '?'}, firmware {device.get('firmware_version', '?')}, "
                 f"logic {version}, chip {device.get('chip_id', '?')}, {info.sensor_hw[1]}x{info.sensor_hw[0]} px"
                 f"{extra}{source}")
    config = {k: v for k, v in info.config.items() if not isinstance(v, (dict, list))}
    lines.append(f"  config        {', '.join(f'{k}={v}' for k, v in config.items()) or 'none stored'}")
    if info.labels is None:
        lines.append("  labels        none")
    else:
        labels = info.labels
        when = (f", {labels.t_first_us} … {labels.t_last_us} µs" if labels.t_first_us is not None else "")
        lines.append(f"  labels        {labels.boxes:,} boxes at {labels.label_times:,} times "
                     f"({_items(labels.boxes_per_class)}){when}")
        made = labels.provenance
        lines.append(f"                made by {made.get('labeler', 'an unknown labeler')} "
                     f"{made.get('labeler_version', '')}".rstrip()
                     + (f" on {made['created_utc']}" if made.get("created_utc") else "")
                     + (f"; source: {made['source']}" if made.get("source") else ""))
    origin = (f"{info.crop_origin_xy[0]}, {info.crop_origin_xy[1]} (stored with the labels)" if info.crop_origin_xy
              else "not stored (the commands use the centred crop)")
    lines.append(f"  crop origin   {origin}")
    if info.biases:
        lines.append(f"  biases        {len(info.biases)} stored:")
        for name, value in info.biases.items():
            fields = (" ".join(f"{k}={v}" for k, v in value.items()) if isinstance(value, dict) else str(value))
            lines.append(f"    {name:<18}{fields}")
    else:
        lines.append("  biases        none stored")
    return lines


def _replay_text(info) -> list[str]:
    cut = ", the last record was cut short and is ignored" if info.truncated else ""
    return [f"{info.path}: DAVIS raw USB replay (not a session: davis-record --fake {info.path} records it into "
            f"one), {_size(info.file_size_bytes)}",
            f"  camera        serial {info.serial or '?'}, firmware {info.firmware_version}, logic "
            f"{info.logic_version}, {info.sensor_hw[1]}x{info.sensor_hw[0]} px",
            f"  transfers     {info.transfers:,} ({_size(info.transfer_bytes)}) over "
            f"{info.host_duration_us / 1e6:.3f} s "
            f"of host time{cut}",
            f"  duration      {_span(info.t_first_event_us, info.t_last_event_us, info.duration_us)}",
            f"  events        {info.events:,}  mean {_rate(info.event_rate_mean_hz)}ev/s",
            f"  APS frames    {info.frames:,}",
            f"  IMU samples   {info.imu_samples:,}",
            f"  specials      {info.specials:,}",
            f"  decoder       {_items(info.decoder_counters)}"]


def _run(args) -> int:
    results, code = [], EXIT_OK
    for name in args.files:
        path = Path(name)
        try:
            kind, info = describe(path)
        except (DavisRigError, OSError) as exc:  # every file gets its own message; bugs keep their traceback
            print(f"{NAME}: error: {error_message(exc)}", file=sys.stderr)
            code = max(code, exit_code_for(exc))
            continue
        if args.json:
            results.append({"kind": kind, **info.to_json()})
        else:
            print("\n".join(_session_text(info) if kind == "session" else _replay_text(info)))
    if args.json and results:
        print(json.dumps(results[0] if len(args.files) == 1 else results, indent=1))
    return code


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-info``; returns the exit code (4 when a file could not be described)."""
    return run_main(build_parser(), argv, _run)


if __name__ == "__main__":
    sys.exit(main())
