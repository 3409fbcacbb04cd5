"""Fuzz campaign of the capture path: corrupt DAVIS346 byte streams through decoder + writer + recovery.

Run: ``python benchmarks/fuzz_capture.py [--seeds 1000] [--events 20000] [--garbage-seeds 10]``

Each seed builds a valid stream (DVS events with distinct (x, y, p) at ``--rate`` events/s plus a 16×12 APS
frame every 5 ms, encoded by :class:`~davis_rig.protocol.encoder.StreamEncoder`) and damages it with one kind of
corruption, in turn:

* ``random_words``: 1-4 stretches of 2-512 random bytes written over the stream;
* ``bit_flips``: 1-32 single-bit flips;
* ``byte_shift``: 1-3 bytes removed or inserted at one place (a shifted record: everything after is misaligned);
* ``truncation``: the stream cut at a random byte (odd cuts included);
* ``huge_jumps``: 1-4 insertions of a 4095 wrap word, 1-300 of them (up to 11 h), a timestamp reset, a timestamp
  word 0xFFFF or a run of random timestamp words;
* ``garbage``: every byte replaced by a random one with probability 1e-3 (the fault model of
  ``usb.sources.Faults.garbage_rate``);
* ``noise``: the whole stream replaced by random bytes of the same length.

The damaged stream is cut into 8 KiB transfers and written twice: live (``StreamDecoder.feed`` →
``SessionWriter.append``) and through a crash (the transfers journaled by ``SessionJournal``, then
``recover_session``). Checks per case: no exception anywhere; both files readable and equal; every event decoded
from the intact prefix (the bytes before the first damaged one) stored unchanged at the start of the file; the
file's ``ms_to_idx`` no longer than the span the writer may create (``max_gap_us`` per event run and per other
item). The process runs under an address-space limit (``--memory-limit-mb``) so a runaway allocation fails fast
instead of meeting the OOM killer; its peak resident set size is reported.

A second part measures the share of valid events kept at a garbage rate of ``--garbage-rate`` (default 1e-4) on
``--garbage-seeds`` streams of 179,920 events (every (x, y, p) once, so an event is kept when its address is in
the file).
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
from _common import metadata_line

from davis_rig.protocol import ApsFrame, SensorLayout, StreamDecoder, StreamEncoder
from davis_rig.session.journal import SessionJournal, journal_path
from davis_rig.session.reader import SessionReader
from davis_rig.session.recovery import recover_session
from davis_rig.session.writer import MAX_GAP_US, SessionWriter
from davis_rig.types import make_events

LAYOUT = SensorLayout.davis346()
KINDS = ("random_words", "bit_flips", "byte_shift", "truncation", "huge_jumps", "garbage", "noise")
TRANSFER_BYTES = 8192
#: Distinct (x, y, p) of a DAVIS346: the largest stream in which every event can be told apart by its address.
MAX_DISTINCT_EVENTS = 346 * 260 * 2
FRAME_PERIOD_US = 5000
FRAME_HW = (12, 16)
CAMPAIGN_GARBAGE_RATE = 1e-3


class CaseResult(NamedTuple):
    """Outcome of one fuzz case (``error`` is the traceback text of an exception, else empty)."""

    kind: str
    seed: int
    error: str = ""
    prefix_events: int = 0
    prefix_kept: int = 0
    events: int = 0
    ms_entries: int = 0
    ms_bound: int = 0
    files_equal: bool = True
    seconds: float = 0.0


def clean_stream(seed: int, n_events: int, rate_hz: float) -> tuple[np.ndarray, bytes]:
    """A valid DAVIS346 stream: ``n_events`` events with distinct (x, y, p) at ``rate_hz`` plus small APS frames.

    Returns:
        (events EVENT_DTYPE [N], the encoded little-endian bytes).
    """
    rng = np.random.default_rng(seed)
    n = min(n_events, MAX_DISTINCT_EVENTS)
    keys = rng.permutation(MAX_DISTINCT_EVENTS)[:n]
    span_us = max(int(n / rate_hz * 1e6), 1)
    t = np.sort(rng.integers(0, span_us, n))
    events = make_events(t, keys % 346, (keys // 346) % 260, keys // (346 * 260))
    height, width = FRAME_HW
    frames = []
    for sof in range(1000, span_us - 1000, FRAME_PERIOD_US):
        pixels = (rng.integers(0, 1024, FRAME_HW) << 6).astype(np.uint16)
        x0, y0 = int(rng.integers(0, 346 - width)), int(rng.integers(0, 260 - height))
        frames.append(ApsFrame(pixels, x0, y0, sof, sof + 100, sof + 600, sof + 900))
    return events, StreamEncoder(LAYOUT).encode(events, frames)


def corrupt(data: bytes, kind: str, rng: np.random.Generator, garbage_rate: float = CAMPAIGN_GARBAGE_RATE):
    """Damage a stream.

    Returns:
        (damaged bytes, index of the first damaged byte; ``len(data)`` when nothing before the end was damaged).
    """
    arr = np.frombuffer(data, np.uint8).copy()
    size = arr.shape[0]
    if kind == "random_words":
        starts = rng.integers(0, size, int(rng.integers(1, 5)))
        for start in starts.tolist():
            stop = min(size, start + int(rng.integers(2, 513)))
            arr[start:stop] = rng.integers(0, 256, stop - start, dtype=np.uint8)
        return arr.tobytes(), int(starts.min())
    if kind == "bit_flips":
        where = rng.integers(0, size * 8, int(rng.integers(1, 33)))
        np.bitwise_xor.at(arr, where // 8, (1 << (where % 8)).astype(np.uint8))
        return arr.tobytes(), int(where.min() // 8)
    if kind == "byte_shift":
        at, count = int(rng.integers(0, size)), int(rng.integers(1, 4))
        if rng.random() < 0.5:
            return data[:at] + data[at + count :], at
        return data[:at] + rng.integers(0, 256, count, dtype=np.uint8).tobytes() + data[at:], at
    if kind == "truncation":
        at = int(rng.integers(0, size + 1))
        return data[:at], at
    if kind == "huge_jumps":
        return _insert_jumps(data, rng)
    if kind == "noise":
        return rng.integers(0, 256, size, dtype=np.uint8).tobytes(), 0
    if kind == "garbage":
        hit = rng.random(size) < garbage_rate
        arr[hit] = rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
        return arr.tobytes(), int(np.argmax(hit)) if hit.any() else size
    raise ValueError(f"unknown corruption kind {kind!r}")


def _insert_jumps(data: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """Insert 1-4 time-jump word groups at word boundaries."""
    words = np.frombuffer(data[: len(data) // 2 * 2], "<u2")
    at = np.sort(rng.integers(0, words.shape[0] + 1, int(rng.integers(1, 5))))
    pieces, last = [], 0
    for pos in at.tolist():
        choice = int(rng.integers(0, 5))
        if choice == 0:
            jump = [0x7FFF]  # wrap × 4095: +134 s
        elif choice == 1:
            jump = [0x7FFF] * int(rng.integers(1, 301))  # up to 11 h, crossing big wraps
        elif choice == 2:
            jump = [0x0001]  # timestamp reset
        elif choice == 3:
            jump = [0xFFFF]  # timestamp word 32767
        else:
            jump = (0x8000 | rng.integers(0, 0x8000, int(rng.integers(1, 20)))).tolist()
        pieces += [words[last:pos], np.array(jump, "<u2")]
        last = pos
    pieces.append(words[last:])
    return np.concatenate(pieces).astype("<u2").tobytes() + data[len(data) // 2 * 2 :], int(at[0]) * 2


def transfers_of(data: bytes) -> list[bytes]:
    """Cut a stream into libcaer-sized transfers."""
    return [data[i : i + TRANSFER_BYTES] for i in range(0, len(data), TRANSFER_BYTES)]


def write_live(path: Path, transfers: list[bytes]) -> None:
    """Decode and write the transfers as a recording does."""
    decoder = StreamDecoder(LAYOUT)
    with SessionWriter(path, device_info={"layout": LAYOUT.to_dict()}, overwrite=True) as writer:
        for transfer in transfers:
            writer.append(decoder.feed(transfer))
        writer.set_stats({"decoder": decoder.stats.as_dict()})


def write_recovered(path: Path, transfers: list[bytes]) -> None:
    """Journal the transfers as a recording that crashed, then rebuild the file with ``recover_session``."""
    header = {"format": "davis_rig.journal", "device_info": {"layout": LAYOUT.to_dict()}, "config": {}}
    journal = SessionJournal(journal_path(path), header).open()
    for transfer in transfers:
        journal.append_transfer(transfer)
    journal.close(delete=False)
    recover_session(path)


def ms_bound(reader: SessionReader, max_gap_us: int) -> int:
    """Most ``ms_to_idx`` entries the writer may create: the events' span at most ``max_gap_us`` per event run
    and per other item (frames, specials, IMU samples) that may bridge a gap, plus the sentinel."""
    t = reader.events()["t"]
    runs = int(np.count_nonzero(np.diff(t))) + 1 if t.shape[0] else 0
    others = len(reader.frames) + len(reader.specials()) + (len(reader.imu()) if reader.imu() is not None else 0)
    return (runs + others) * (max_gap_us // 1000 + 1) + 2


def run_case(seed: int, kind: str, workdir: Path, n_events: int, rate_hz: float) -> CaseResult:
    """One fuzz case (see the module docstring); exceptions are caught and returned in ``error``."""
    start = time.perf_counter()
    try:
        events, data = clean_stream(seed, n_events, rate_hz)
        damaged, first = corrupt(data, kind, np.random.default_rng(seed + 7919))
        prefix = StreamDecoder(LAYOUT).feed(data[: first - first % 2]).events
        transfers = transfers_of(damaged)
        live, recovered = workdir / f"{kind}_{seed}.h5", workdir / f"{kind}_{seed}_recovered.h5"
        write_live(live, transfers)
        write_recovered(recovered, transfers)
        with SessionReader(live) as a, SessionReader(recovered) as b:
            stored = a.events()
            head = stored[: prefix.shape[0]]
            result = CaseResult(
                kind, seed,
                prefix_events=prefix.shape[0],
                prefix_kept=int(np.count_nonzero(head == prefix)) if head.shape == prefix.shape else 0,
                events=stored.shape[0],
                ms_entries=a.ms_to_idx.shape[0],
                ms_bound=ms_bound(a, MAX_GAP_US),
                files_equal=bool(np.array_equal(stored, b.events()) and len(a.frames) == len(b.frames)),
            )
        live.unlink()
        recovered.unlink()
    except Exception:  # noqa: BLE001 - the campaign counts every exception, whatever its type
        result = CaseResult(kind, seed, error=traceback.format_exc())
    return result._replace(seconds=time.perf_counter() - start)


def garbage_kept(seed: int, rate: float, workdir: Path) -> tuple[int, int]:
    """(valid events, valid events whose address is in the file) for one stream at garbage ``rate``."""
    events, data = clean_stream(seed, MAX_DISTINCT_EVENTS, 300_000)
    damaged, _ = corrupt(data, "garbage", np.random.default_rng(seed + 104729), garbage_rate=rate)
    path = workdir / f"garbage_{seed}.h5"
    write_live(path, transfers_of(damaged))
    with SessionReader(path) as reader:
        stored = reader.events()
    path.unlink()
    key = lambda e: (e["p"].astype(np.int64) * 260 + e["y"]) * 346 + e["x"]  # noqa: E731
    return events.shape[0], int(np.isin(key(events), key(stored)).sum())


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def campaign(seeds: int, n_events: int, rate_hz: float, workdir: Path) -> list[CaseResult]:
    """Run ``seeds`` cases, the kinds taken in turn."""
    return [run_case(seed, KINDS[seed % len(KINDS)], workdir, n_events, rate_hz) for seed in range(seeds)]


def summary_lines(results: list[CaseResult]) -> list[str]:
    """Per-kind and total figures of a campaign."""
    lines = []
    for kind in (*KINDS, "all"):
        cases = [r for r in results if kind in ("all", r.kind)]
        if not cases:
            continue
        errors = sum(bool(r.error) for r in cases)
        prefix = sum(r.prefix_events for r in cases)
        kept = sum(r.prefix_kept for r in cases)
        over = sum(r.ms_entries > r.ms_bound for r in cases if not r.error)
        unequal = sum(not r.files_equal for r in cases if not r.error)
        worst = max((r.ms_entries / max(r.events, 1) for r in cases if not r.error), default=0.0)
        lines.append(
            f"  {kind:12s} cases {len(cases):5d}  exceptions {errors}  events before first damage kept "
            f"{kept}/{prefix}  ms_to_idx over bound {over}  live != recovered {unequal}  "
            f"max ms_to_idx entries/event {worst:8.2f}  median {np.median([r.seconds for r in cases]) * 1e3:6.0f} ms"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1000, help="fuzz cases (kinds in turn)")
    parser.add_argument("--events", type=int, default=20_000, help="valid events per fuzz stream (<= 179920)")
    parser.add_argument("--rate", type=float, default=300_000, help="event rate of the valid streams, events/s")
    parser.add_argument("--garbage-rate", type=float, default=1e-4, help="byte garbage rate of the kept-share part")
    parser.add_argument("--garbage-seeds", type=int, default=10, help="streams of the kept-share part (0: skip)")
    parser.add_argument("--memory-limit-mb", type=int, default=4096, help="address-space limit of this process")
    parser.add_argument("--workdir", type=Path, default=None, help="where the session files go (default: a temp dir)")
    args = parser.parse_args(argv)
    if args.memory_limit_mb:
        limit = args.memory_limit_mb << 20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    warnings.simplefilter("ignore")  # every damaged file warns; the figures below count what happened
    logging.disable(logging.WARNING)  # and so does every decoder
    print(metadata_line(("numpy", "h5py", "hdf5plugin"), seeds=args.seeds, events=args.events,
                        memory_limit_mb=args.memory_limit_mb))
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        workdir = Path(tmp)
        start = time.perf_counter()
        results = campaign(args.seeds, args.events, args.rate, workdir)
        print(f"fuzz campaign: {args.seeds} seeds x {args.events} events at {args.rate:g} ev/s, "
              f"{time.perf_counter() - start:.1f} s")
        for line in summary_lines(results):
            print(line)
        for failed in [r for r in results if r.error][:3]:
            print(f"  first exceptions: {failed.kind} seed {failed.seed}:\n{failed.error}")
        if args.garbage_seeds:
            pairs = [garbage_kept(seed, args.garbage_rate, workdir) for seed in range(args.garbage_seeds)]
            valid, kept = (sum(values) for values in zip(*pairs))
            print(f"garbage rate {args.garbage_rate:g}: {kept}/{valid} valid events kept ({100 * kept / valid:.3f} %) "
                  f"over {args.garbage_seeds} streams of {MAX_DISTINCT_EVENTS} events at 300000 ev/s")
    print(f"peak RSS {peak_rss_mb():.0f} MB")
    print(json.dumps({"exceptions": sum(bool(r.error) for r in results), "peak_rss_mb": round(peak_rss_mb())}))
    return 0 if not any(r.error for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
