"""One victim's controls, written as ``<stem>.json`` and ``<stem>.md``: fingerprint and free-appearance bound.

:func:`victim_controls` runs both on the digital evaluation protocol (:mod:`davis_rig.attack.evaluate`) for one
detector: the fingerprint on every test scene, the bound on ``scenes_per_scale`` scenes of each scale (the
optimisation costs ``2 * steps`` detector passes per scene). Each finished part is kept in the output folder
(``fingerprint.json``, ``bound/scene_XXX.npz``) with the detector name, protocol and settings it was made for,
so an interrupted run continues where it stopped, and a part made for another run is refused, never mixed in.

:func:`shared_texture_control` steps from the per-scene bound towards the attack: one grey texture fitted to the
bound's scenes together, scored grey and binarized on those scenes and on the others (held out).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from davis_rig.controls.bounds import BOUND_KINDS, BoundConfig, bound_rows, fingerprint_textures
from davis_rig.errors import ConfigError

__all__ = ["bound_scene_indices", "paper_fingerprint", "shape_split_indices", "shared_texture_control",
           "victim_controls"]


def bound_scene_indices(scales: Sequence[str], per_scale: int) -> list[int]:
    """Indices of ``per_scale`` scenes of each scale, evenly spread over that scale's scenes.

    Args:
        scales: the scale of every scene, in the evaluation's order.
        per_scale: scenes to keep per scale (all of a scale when it has fewer).

    Returns:
        Sorted indices into ``scales``.
    """
    if int(per_scale) < 1:
        raise ValueError(f"per_scale must be >= 1, got {per_scale}")
    out = []
    for scale in dict.fromkeys(scales):
        idx = [i for i, s in enumerate(scales) if s == scale]
        picks = np.unique(np.linspace(0, len(idx) - 1, min(int(per_scale), len(idx))).round().astype(int))
        out += [idx[k] for k in picks]
    return sorted(out)


def shape_split_indices(shapes: Sequence[int], fit_shapes: int) -> list[int]:
    """Indices of every scene of the first ``fit_shapes`` distinct body shapes (in order of first appearance).

    The other scenes then show only bodies the fitted scenes never showed: a held-out set of new people, not
    the same people at other headings, phases or scales.

    Args:
        shapes: the body shape index of every scene, in the evaluation's order.
        fit_shapes: how many distinct shapes to take (1 ... number of distinct shapes − 1, so that some are left).

    Returns:
        Sorted indices into ``shapes``.

    Raises:
        ConfigError: ``fit_shapes`` leaves no shape out, or is below 1.
    """
    distinct = list(dict.fromkeys(int(s) for s in shapes))
    if not 1 <= int(fit_shapes) < len(distinct):
        raise ConfigError("fit_shapes", f"expected an integer in [1, {len(distinct) - 1}] (the scenes show "
                                        f"{len(distinct)} bodies, and one must be left out), got {fit_shapes}")
    chosen = set(distinct[: int(fit_shapes)])
    return [i for i, s in enumerate(shapes) if int(s) in chosen]


def paper_fingerprint(ap_by_texture: dict) -> bool:
    """Whether a victim shows the paper's fingerprint: white has the highest AP of white, black and random 60x60
    at the threshold (the paper's victim: 50.5 against 43.8 and 45.2 at 0.25)."""
    white = ap_by_texture["white"]
    return white > ap_by_texture["black"] and white > ap_by_texture["random 60x60"]


def _pct(value) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{100.0 * value:.1f}"


def victim_controls(detector, out_dir, *, name: str, eval_config, bound_config: BoundConfig | None = None,
                    scenes_per_scale: int = 4, command: str = "", detector_name: str = "",
                    fingerprint: bool = True, bound: bool = True, model=None,
                    progress: Callable[[str], None] | None = None) -> dict:
    """Fingerprint and free-appearance bound of one detector (see the module docstring).

    Args:
        detector: frozen RVT detector.
        out_dir: folder of the run's parts and of ``controls_<name>.json`` / ``.md``.
        name: the victim's name (file stem and title).
        eval_config: :class:`~davis_rig.attack.evaluate.EvalConfig` (its thresholds score the fingerprint; the
            bound is scored at ``bound_config.threshold``).
        bound_config: the free-appearance optimisation (default :class:`BoundConfig`).
        scenes_per_scale: test scenes per scale of the bound.
        command, detector_name: recorded in the report.
        fingerprint, bound: which parts to run.
        model: :class:`~davis_rig.scene.body.BodyModel` (default the bundled asset).
        progress: optional callable ``(message) -> None``.

    Returns:
        The report dict written to ``controls_<name>.json``.

    Raises:
        ConfigError: (field ``out_dir``) a kept part of ``out_dir`` was made for another detector name, protocol
            or bound settings: a rerun continues only the run that made it.
    """
    bound_config = bound_config or BoundConfig()
    out, model, say, specs = _prepare_run(out_dir, model, progress, eval_config)
    report = {**_provenance(name, detector_name, command),
              "eval_config": _eval_config_record(eval_config)}
    if fingerprint:
        report["fingerprint"] = _fingerprint_section(detector, out, specs, model, eval_config, bound_config,
                                                     detector_name, say)
    if bound:
        report["bound"] = _bound_section(detector, out / "bound", specs, model, eval_config, bound_config,
                                         scenes_per_scale, detector_name, say)
    (out / f"controls_{name}.json").write_text(json.dumps(report, indent=1))
    (out / f"controls_{name}.md").write_text(_markdown(report))
    return report


def _fingerprint_section(detector, out: Path, specs, model, eval_config, bound_config: BoundConfig,
                         detector_name: str, say: Callable[[str], None]) -> dict:
    """The baseline textures scored on every test scene (reuses ``out/fingerprint.json`` when it was scored for
    the same detector name, textures and protocol; refuses one scored otherwise)."""
    from davis_rig.attack.evaluate import evaluate_textures, prepare_scenes
    from davis_rig.attack.report import results_markdown

    done = out / "fingerprint.json"
    made_for = json.loads(json.dumps({"detector": detector_name, "grid_n": int(bound_config.grid_n),
                                      "parts": bound_config.parts,
                                      "protocol": {**_scene_protocol(eval_config),
                                                   "thresholds": list(eval_config.thresholds)}}))
    if done.is_file():
        kept = json.loads(done.read_text())
        if not isinstance(kept, dict) or kept.get("made_for") != made_for:
            raise ConfigError("out_dir", f"{done} was scored for another detector, textures or protocol (or before "
                                         f"they were recorded): give another output folder, or delete it to score "
                                         "again")
        rows = kept["rows"]
    else:
        scenes = prepare_scenes(specs, model, eval_config)
        say(f"fingerprint: {len(scenes)} scenes x {len(fingerprint_textures(bound_config.grid_n))} textures")
        rows = evaluate_textures(fingerprint_textures(bound_config.grid_n, bound_config.parts), detector, scenes,
                                 eval_config)
        done.with_suffix(".tmp").write_text(json.dumps({"made_for": made_for, "rows": rows}, indent=1))
        done.with_suffix(".tmp").replace(done)
    at = max(eval_config.thresholds)
    ap = {r["texture"]: r["AP"] for r in rows if r["scale"] == "all" and math.isclose(r["threshold"], at)}
    return {"rows": rows, "threshold": at, "paper_fingerprint": paper_fingerprint(ap),
            "markdown": results_markdown(rows, eval_config.thresholds)}


def _bound_section(detector, folder: Path, specs, model, eval_config, bound_config: BoundConfig,
                   scenes_per_scale: int, detector_name: str, say: Callable[[str], None]) -> dict:
    """The free-appearance bound on ``scenes_per_scale`` scenes per scale, one resumable part file per scene."""
    import time

    from davis_rig.attack.evaluate import prepare_scenes

    keep = bound_scene_indices([str(s) for s, _ in specs], scenes_per_scale)
    folder.mkdir(exist_ok=True)
    names = ["white", "black", *bound_config.kinds]
    decoded = {n: [] for n in names}
    per_scene, scored = [], []
    t0 = time.perf_counter()
    for k, index in enumerate(keep):
        scene = prepare_scenes([specs[index]], model, eval_config)[0]
        record, scene_decoded = _bound_of_scene(folder / f"scene_{index:03d}.npz", scene, detector, eval_config,
                                                bound_config, names, detector_name)
        for n in names:
            decoded[n].append(scene_decoded[n])
        record["scene"] = index
        per_scene.append(record)
        scored.append(scene)
        say(f"bound: scene {k + 1}/{len(keep)} ({record['scale']}): "
            + ", ".join(f"{n} {record[n]:.3f}" for n in names))
    rows = bound_rows(decoded, scored, per_scene, bound_config.threshold, eval_config)
    return {"threshold": bound_config.threshold, "scenes": len(scored), "rows": rows,
            "per_scene": per_scene, "config": {"steps": bound_config.steps, "lr": bound_config.lr,
                                               "grid_n": bound_config.grid_n, "parts": bound_config.parts,
                                               "kinds": list(bound_config.kinds)},
            "seconds_this_call": time.perf_counter() - t0}


def _bound_of_scene(part: Path, scene, detector, eval_config, bound_config: BoundConfig,
                    names: list[str], detector_name: str = "") -> tuple[dict, dict]:
    """One scene's bound: the appearances of ``names`` not yet in ``part`` are computed and saved to it (atomically,
    beside those already there); returns the scene's record and, per appearance name, its decoded detections per
    window. A part is extended or reused only when it was made with the same bound settings, detector name, scene
    and protocol (:func:`_scene_protocol`)."""
    from dataclasses import replace

    from davis_rig.attack.evaluate import TextureSpec
    from davis_rig.attack.texture import black_texture, white_texture
    from davis_rig.controls.bounds import free_appearance_bound

    windows = range(len(scene.window_end_us))
    settings = _bound_settings(bound_config, detector_name, eval_config, scene)
    record, decoded = {}, {}
    if part.is_file():
        with np.load(part) as data:
            record = json.loads(str(data["record"]))
            decoded = {n: [data[f"{n}__{w}"] for w in windows] for n in record if f"{n}__0" in data}
        if record.get("settings") != settings:
            differ = _differing_fields(settings, record.get("settings") or {})
            raise ConfigError("out_dir", f"{part} was made with other bound settings (other {', '.join(differ)}): "
                                         f"give another output folder, or delete {part.parent} to start over")
    missing = [n for n in names if n not in decoded]
    if missing:
        plain = {"white": white_texture(1), "black": black_texture(1)}
        baselines = {n: TextureSpec(plain[n], bound_config.parts) for n in missing if n in plain}
        kinds = tuple(n for n in BOUND_KINDS if n in missing)
        res = free_appearance_bound([scene], detector, eval_config, replace(bound_config, kinds=kinds),
                                    baselines=baselines)
        record.update(res["per_scene"][0], settings=settings)
        decoded.update({n: res["decoded"][n][0] for n in missing})
        np.savez(part.with_suffix(".tmp.npz"), record=json.dumps(record),
                 **{f"{n}__{w}": d[w] for n, d in decoded.items() for w in windows})
        part.with_suffix(".tmp.npz").replace(part)
    kept = {k: v for k, v in record.items() if k in ("scene", "scale", "shape", "heading_rad") or k in names}
    return kept, {n: decoded[n] for n in names}


def shared_texture_control(detector, out_dir, *, name: str, eval_config, bound_config: BoundConfig | None = None,
                           scenes_per_scale: int = 1, fit_shapes: int | None = None, command: str = "",
                           detector_name: str = "", model=None, binary: bool = False,
                           progress: Callable[[str], None] | None = None) -> dict:
    """One grey texture fitted to the bound's scenes at once, scored where it was fitted and on held-out scenes.

    Steps: :func:`~davis_rig.controls.bounds.optimise_shared_texture` on the ``scenes_per_scale`` scenes per scale
    of the bound (:func:`bound_scene_indices`; kept as ``shared_texture[_binary].npy``, with a ``.json`` of the
    scenes, settings and detector it was fitted to, so a rerun of the same fit scores it again and another fit in
    the same folder is refused); then
    white, black, the grey texture and its binarization (``> 0.5``) scored with
    :func:`~davis_rig.attack.evaluate.evaluate_textures` on those scenes ("fitted") and on every other scene of the
    protocol ("held out"). Where the per-scene ``"static texture"`` bound blinds a victim and this texture does not,
    no single print of that grid does on those scenes; where the grey texture does and its binarization not, the
    black/white constraint is what costs.

    Args:
        detector: frozen RVT detector.
        out_dir: folder of ``shared_texture.npy``, ``shared_<name>.json`` / ``.md``.
        name: file stem and title.
        eval_config: :class:`~davis_rig.attack.evaluate.EvalConfig` (the protocol and its thresholds).
        bound_config: the optimisation (``grid_n``, ``parts``, ``steps``, ``lr``, ``threshold``, ``theta``,
            ``events``: the evaluation's event model).
        scenes_per_scale: fitted scenes per scale.
        fit_shapes: instead of ``scenes_per_scale``: fit every scene of the first ``fit_shapes`` test bodies
            (:func:`shape_split_indices`), so that the held-out scenes show other people.
        command, detector_name: recorded in the report.
        model: :class:`~davis_rig.scene.body.BodyModel` (default the bundled asset).
        binary: fit the black/white texture itself (straight-through gradient) instead of a grey one; the report
            then scores it alone (``shared binary-fitted``).
        progress: optional callable ``(message) -> None``.

    Returns:
        The report dict written to ``shared_<name>.json``.

    Raises:
        ConfigError: (field ``out_dir``) ``out_dir`` keeps a texture of another fit, or one without its record.
        ValueError: the bound's event model is not the evaluation's
            (:func:`~davis_rig.controls.bounds.check_event_model`).
    """
    import time

    from davis_rig.attack.evaluate import TextureSpec, evaluate_textures, prepare_scenes
    from davis_rig.attack.report import results_markdown
    from davis_rig.attack.texture import black_texture, hard_binarize, white_texture
    from davis_rig.controls.bounds import check_event_model, optimise_shared_texture
    from davis_rig.scene.masks import part_mask

    config = bound_config or BoundConfig()
    check_event_model(config, eval_config)
    out, model, say, specs = _prepare_run(out_dir, model, progress, eval_config)
    fitted = (bound_scene_indices([str(s) for s, _ in specs], scenes_per_scale) if fit_shapes is None
              else shape_split_indices([spec.shape_index for _, spec in specs], fit_shapes))
    held_out = [i for i in range(len(specs)) if i not in fitted]
    t0 = time.perf_counter()
    kept = out / ("shared_texture_binary.npy" if binary else "shared_texture.npy")
    fit = _shared_fit_record(config, binary, detector_name, eval_config, [specs[i] for i in fitted])
    if kept.is_file():
        grey = _kept_shared_texture(kept, fit)
    else:
        scenes = prepare_scenes([specs[i] for i in fitted], model, eval_config)
        say(f"fitting one {config.grid_n}x{config.grid_n} {'black/white' if binary else 'grey'} texture to "
            f"{len(scenes)} scenes, {config.steps} steps")
        mask = part_mask(config.parts) if config.parts is not None else None
        grey = optimise_shared_texture(scenes, detector, config, mask, binary=binary, eval_config=eval_config)
        kept.with_suffix(".json").write_text(json.dumps(fit, indent=1) + "\n")
        np.save(kept.with_suffix(".tmp.npy"), grey)
        kept.with_suffix(".tmp.npy").replace(kept)
    fit_s = time.perf_counter() - t0
    n = config.grid_n
    textures = {"white": TextureSpec(white_texture(1), config.parts),
                "black": TextureSpec(black_texture(1), config.parts)}
    if binary:
        textures[f"shared binary-fitted {n}x{n}"] = TextureSpec(hard_binarize(grey), config.parts)
    else:
        textures[f"shared grey {n}x{n}"] = TextureSpec(grey.astype(np.float32), config.parts)
        textures[f"shared binary {n}x{n}"] = TextureSpec(hard_binarize(grey), config.parts)
    report = {**_provenance(name, detector_name, command),
              "config": {"grid_n": n, "parts": config.parts, "steps": config.steps, "lr": config.lr,
                         "threshold": config.threshold, "theta": config.theta, "binary": bool(binary),
                         "fit_shapes": fit_shapes},
              "eval_config": _eval_config_record(eval_config),
              "fitted_scenes": fitted, "held_out_scenes": held_out, "fit_seconds_this_call": fit_s,
              "white_cells": float(hard_binarize(grey).mean())}
    for key, indices in (("fitted", fitted), ("held_out", held_out)):
        if not indices:
            continue
        say(f"scoring on the {len(indices)} {key.replace('_', '-')} scenes")
        rows = evaluate_textures(textures, detector, prepare_scenes([specs[i] for i in indices], model, eval_config),
                                 eval_config)
        report[key] = {"rows": rows, "markdown": results_markdown(rows, eval_config.thresholds)}
    (out / f"shared_{name}.json").write_text(json.dumps(report, indent=1))
    lines = [f"# One shared grey texture: `{name}`", "", f"Detector: {detector_name}. Measured {report['measured']} "
             f"on {report['machine']}. " + _protocol_line(report["eval_config"]), ""]
    if command:
        lines += ["```bash", command, "```", ""]
    what = ("black/white (straight-through gradient)" if binary else "grey")
    lines += [f"One free {what} {n}x{n} texture on {config.parts or 'the whole body'} fitted to {len(fitted)} scenes "
              f"together ({config.steps} Adam steps, lr {config.lr:g}, hinge at {config.threshold:g}); "
              f"{report['white_cells']:.0%} of its cells are white (> 0.5; cells no fitted scene shows stay at "
              f"{'their start' if binary else '0.5, i.e. black'})."]
    if fit_shapes is not None:
        fit_bodies = sorted({specs[i][1].shape_index for i in fitted})
        other_bodies = sorted({specs[i][1].shape_index for i in held_out})
        lines[-1] += (f" The fitted scenes are every scene of test bodies {fit_bodies}; the held-out ones show only "
                      f"bodies {other_bodies}, never fitted.")
    lines.append("")
    for key, title in (("fitted", "On the scenes it was fitted to"), ("held_out", "On the held-out scenes")):
        if key in report:
            lines += [f"## {title} ({len(report[key + '_scenes'])} scenes, AP % / SeqASR %)", "",
                      report[key]["markdown"], ""]
    (out / f"shared_{name}.md").write_text("\n".join(lines))
    return report


def _shared_fit_record(config: BoundConfig, binary: bool, detector_name: str, eval_config, fitted_specs) -> dict:
    """What a shared texture was fitted to, as JSON values: the optimisation's settings, the detector's name, the
    scene protocol (:func:`_scene_protocol`, with the event model) and every fitted scene (:func:`_scene_key`)."""
    return json.loads(json.dumps({
        "grid_n": config.grid_n, "parts": config.parts, "steps": config.steps, "lr": config.lr,
        "threshold": config.threshold, "theta": config.theta, "binary": bool(binary), "detector": detector_name,
        "scenes": [_scene_key(scale, spec) for scale, spec in fitted_specs],
        "protocol": _scene_protocol(eval_config)}))


def _kept_shared_texture(kept: Path, fit: dict) -> np.ndarray:
    """The texture kept by an earlier call, when its record (``kept`` with ``.json``) says it was fitted as ``fit``.

    Raises:
        ConfigError: (field ``out_dir``) no record beside it, or one of another fit (other scenes, settings or
            detector): scoring it would report a texture as fitted to scenes it never saw.
    """
    record_path = kept.with_suffix(".json")
    if not record_path.is_file():
        raise ConfigError("out_dir", f"{kept} has no {record_path.name} saying what it was fitted to: give another "
                                     "output folder, or remove it to fit again")
    record = json.loads(record_path.read_text())
    differ = _differing_fields(fit, record)
    if differ:
        raise ConfigError("out_dir", f"{kept} was fitted with other {', '.join(differ)} than this call's: give "
                                     "another output folder, or remove it to fit again")
    return np.load(kept)


def _prepare_run(out_dir, model, progress, eval_config) -> tuple[Path, object, Callable[[str], None], list]:
    """``(out folder (created), body model (default the bundled asset), progress callable, the protocol's scene
    specs)`` of a controls run."""
    from davis_rig.attack.evaluate import evaluation_scenes
    from davis_rig.scene.body import BodyModel

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = model or BodyModel()
    return out, model, progress or (lambda message: None), evaluation_scenes(eval_config, model.num_shapes)


def _provenance(name: str, detector_name: str, command: str) -> dict:
    """The fields every controls report starts with: what was measured, with which command, when and where."""
    import platform
    import time

    return {"name": name, "detector": detector_name, "command": command, "measured": time.strftime("%Y-%m-%d"),
            "machine": f"{platform.machine()}, {platform.node()}"}


def _light_name(light) -> str:
    """``"official"`` (:meth:`~davis_rig.scene.shading.Light.official`), ``"toolkit"`` (``None``: the default
    light) or the light's fields."""
    from davis_rig.scene.shading import Light

    if light is None or light == Light():
        return "toolkit"
    return "official" if light == Light.official() else repr(light)


def _eval_config_record(eval_config) -> dict:
    """The evaluation protocol of a report, as JSON values: its scenes (scales, headings, phases, walk, background,
    light, walking in place, playback speed), event model and thresholds."""
    return {"scales": list(map(str, eval_config.scales)), "headings_rad": list(eval_config.headings_rad),
            "phases": list(eval_config.phases), "thresholds": list(eval_config.thresholds),
            "walk": eval_config.walk, "background": float(eval_config.background),
            "light": _light_name(eval_config.light), "walk_in_place": bool(eval_config.walk_in_place),
            "playback_speed": float(eval_config.playback_speed), "events": eval_config.events}


def _scene_protocol(eval_config) -> dict:
    """Everything a kept part's detections depend on besides the detector and the bound's settings, as JSON
    values: the protocol record without its thresholds (they only score), plus the scene list, sequence, rendering,
    NMS and simulator settings. A kept part is reused only under an equal record."""
    from dataclasses import asdict

    record = {k: v for k, v in _eval_config_record(eval_config).items() if k != "thresholds"}
    record.update(shapes=None if eval_config.shapes is None else list(eval_config.shapes),
                  seq_len=int(eval_config.seq_len), window_us=int(eval_config.window_us),
                  warmup_windows=int(eval_config.warmup_windows), nms_threshold=float(eval_config.nms_threshold),
                  render_rate_hz=float(eval_config.render_rate_hz), supersample=int(eval_config.supersample),
                  simulator=asdict(eval_config.simulator))
    return json.loads(json.dumps(record))


def _protocol_line(record: dict) -> str:
    """One sentence naming a report's scenes and event model, from the fields of its protocol record; the
    official code's scene is named only when its background, light and walking in place all are (reports written
    before the light was recorded name it from the other two; before any of these fields: the toolkit's scene and
    exact events, which were then the only ones)."""
    events = record.get("events", "exact")
    background, light = record.get("background", 0.5), record.get("light")
    in_place = bool(record.get("walk_in_place"))
    if in_place and background == 1.0 and light in ("official", None):
        scene = "the official code's scene (blank white background, its light, walking in place)"
    elif not in_place and background == 0.5 and light in ("toolkit", None):
        scene = "the toolkit's scene (grey 0.5 background, walking across)"
    else:
        scene = (f"a scene of background {background:g}, the {light or 'toolkit'} light, "
                 f"walking {'in place' if in_place else 'across'}")
    speed = record.get("playback_speed", 1.0)
    scene += "" if speed == 1.0 else f", played {speed:g}x"
    what = ("the official code's relaxed counts (continuous, not events)" if events == "official_relaxed"
            else "exact events (ideal sensor)")
    return f"Scenes: {scene}, the {record.get('walk', 'natural')} walk; scored on {what}."


def _differing_fields(a: dict, b: dict) -> list[str]:
    """Sorted names of the fields where two records differ; in a field both hold as a record, the names of its
    own differing fields (``protocol`` -> ``walk``, ``background``)."""
    names = set()
    for key in a.keys() | b.keys():
        if isinstance(a.get(key), dict) and isinstance(b.get(key), dict):
            names.update(_differing_fields(a[key], b[key]))
        elif a.get(key) != b.get(key):
            names.add(key)
    return sorted(names)


def _scene_key(scale, spec) -> list:
    """A scene as ``[scale, body shape, heading (rad), walk phase (s)]`` (JSON values)."""
    return json.loads(json.dumps([str(scale), spec.shape_index, spec.heading_rad, spec.motion_start_s]))


def _bound_settings(config: BoundConfig, detector_name: str, eval_config, scene) -> dict:
    """What a kept bound part depends on: every :class:`BoundConfig` field but ``kinds`` (its event model is in the
    protocol), the detector name, the scene protocol (:func:`_scene_protocol`) and the scene."""
    return {"steps": int(config.steps), "lr": float(config.lr), "threshold": float(config.threshold),
            "grid_n": int(config.grid_n), "parts": None if config.parts is None else list(config.parts),
            "theta": float(config.theta), "detector": detector_name, "protocol": _scene_protocol(eval_config),
            "scene": _scene_key(scene.scale, scene.spec)}


def _markdown(report: dict) -> str:
    lines = [f"# Controls of the victim `{report['name']}`", "",
             f"Detector: {report['detector']}. Measured {report['measured']} on {report['machine']}. "
             + _protocol_line(report.get("eval_config", {})), ""]
    if report["command"]:
        lines += ["```bash", report["command"], "```", ""]
    if "fingerprint" in report:
        fp = report["fingerprint"]
        lines += ["## Baseline fingerprint (all scales, AP % / SeqASR %)", "", fp["markdown"], "",
                  f"The paper's fingerprint (white detected best at {fp['threshold']:g}): "
                  f"**{'yes' if fp['paper_fingerprint'] else 'no'}**.", ""]
    if "bound" in report:
        b = report["bound"]
        lines += [f"## Free-appearance bound ({b['scenes']} test scenes, threshold {b['threshold']:g}, "
                  f"{b['config']['steps']} Adam steps per scene)", "",
                  "| appearance | AP % | SeqASR % | mean top score |", "|---|---|---|---|"]
        for r in b["rows"]:
            lines.append(f"| {r['appearance']} | {_pct(r['AP'])} | {_pct(r['SeqASR'])} | {r['mean_top_score']:.3f} |")
        n = b["config"]["grid_n"]
        meaning = {"per-pixel": "a free albedo for every covered sample of every frame",
                   "per-frame texture": f"a free grey {n}x{n} grid on the painted parts, a new one every frame",
                   "static texture": f"a free grey {n}x{n} grid on the painted parts, the same in every frame",
                   "static per-texel": "a free grey albedo for every texel of the 1024x1024 texture on the painted "
                                       "parts, the same in every frame"}
        shown = [r["appearance"] for r in b["rows"] if r["appearance"] in meaning]
        if shown:
            scored = ("on the official relaxed counts" if report.get("eval_config", {}).get("events") ==
                      "official_relaxed" else "with the exact simulator")
            lines += ["", "; ".join(f"{k}: {meaning[k]}" for k in shown)
                      + f"; each optimised per scene, scored {scored}.", ""]
    return "\n".join(lines)
