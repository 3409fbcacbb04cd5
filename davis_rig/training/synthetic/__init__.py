"""Synthetic pedestrian event sequences: scene sampler, exact render → simulate → histogram → label pipeline.

A sequence is a :class:`SyntheticScene` (everything resolved from seeds, JSON-able with :meth:`SyntheticScene.to_dict`)
turned into RVT training data by :func:`render_sequence`. Modules, one concept each:

- :mod:`~davis_rig.training.synthetic.scenes`: what a scene is (:class:`PersonSpec`, :class:`DistractorSpec`,
  :class:`VehicleSpec`, :class:`SyntheticScene`), its ranges (:class:`SyntheticSceneConfig`), the splits and their
  samplers (:func:`sample_scene`, :func:`held_out_scene`);
- :mod:`~davis_rig.training.synthetic.paint`: procedural painting: clothing textures (:func:`clothing_texture`:
  random grey/colour per part, stripes, checks, black/white grids of 10..60 cells, plain white, plain black, the
  paper's random 60 x 60 pattern), the distractor and car layers;
- :mod:`~davis_rig.training.synthetic.render`: :func:`render_sequence`: every person posed
  (:func:`person_motion`: the bundled walk cycle or a generated walk/run), all people rasterized as one mesh (the
  z-buffer resolves who occludes whom), textured and composed over the background (warped per frame when the
  camera moves), distractors and cars; the exact event simulator (per-sequence thresholds, mismatch, refractory
  period, shot noise, leak, low-pass); RVT's stacked histograms of back-to-back 50 ms windows (uint8
  [T, 20, 240, 304]); labels;
- :mod:`~davis_rig.training.synthetic.plan`: datasets: :func:`dataset_plan`, :func:`scene_for_job`,
  :func:`generate_dataset` (``davis-make-dataset``: worker processes, resume, RVT's layout and a dataset card).

Labels (Gen1 class 1 = pedestrian, one box per visible person, ``track_id`` = person index): at each window
end (a rendered frame), the tight box of the person's **visible** coverage: samples the person wins in the
z-buffer, times ``1 - alpha`` of the front distractors, pixels with visible coverage > 0. A box is kept when
it passes the Prophesee / RVT Gen1 box filter (diagonal >= 30 px and both sides >= 10 px,
:data:`~davis_rig.metrics.ap.MIN_DIAG_PX`, :data:`~davis_rig.metrics.ap.MIN_SIDE_PX`) and the person shows at
least ``min_visible_px`` px of coverage; people partly outside the frame get the box of their visible part
(as Gen1 annotations). Every window is a labelled frame (an empty array when nobody is visible), so empty
scenes teach the detector to stay silent. Cars, when the config asks for them
(:attr:`SyntheticSceneConfig.vehicle_counts`), get Gen1 class 0 boxes of their visible coverage the same way
(``track_id`` = number of people + car index), so the detector must tell people from cars by their class score.

Cost (measured while generating 27 sequences x 2 s on a shared 2-core CPU, one torch thread, other jobs
running): 6.4 s of wall time per generated second (rasterize 3.4, simulate 1.5, compose 0.7, pose 0.6,
histogram 0.05, label 0.01 s per generated second); see ``benchmarks/synthetic.py``. Use one torch thread per
process (``threads=1``) on a busy machine: oversubscribed intra-op threads made the same scene ~20x slower.

torch is imported lazily (rendering and simulation need it).
"""

from __future__ import annotations

from davis_rig.training.synthetic.paint import clothing_texture
from davis_rig.training.synthetic.plan import (
    GENERATION_FILE,
    SequenceJob,
    dataset_plan,
    generate_dataset,
    scene_for_job,
)
from davis_rig.training.synthetic.render import SyntheticSequence, person_motion, render_sequence
from davis_rig.training.synthetic.scenes import (
    CLOTHING_KINDS,
    DISTRACTOR_KINDS,
    GEN1_LIKE_SCENES,
    PAINT_PATTERNS,
    SCENE_RECIPES,
    SPLIT_SEED_OFFSETS,
    SPLIT_SHAPES,
    SPLIT_SPEEDS_M_S,
    TEST_CLOTHING,
    TEST_SUBSETS,
    DistractorSpec,
    PersonSpec,
    SyntheticScene,
    SyntheticSceneConfig,
    VehicleSpec,
    held_out_scene,
    sample_scene,
)

__all__ = [
    "CLOTHING_KINDS",
    "DISTRACTOR_KINDS",
    "GENERATION_FILE",
    "GEN1_LIKE_SCENES",
    "PAINT_PATTERNS",
    "SCENE_RECIPES",
    "SPLIT_SEED_OFFSETS",
    "SPLIT_SHAPES",
    "SPLIT_SPEEDS_M_S",
    "TEST_CLOTHING",
    "TEST_SUBSETS",
    "DistractorSpec",
    "VehicleSpec",
    "PersonSpec",
    "SyntheticScene",
    "SyntheticSceneConfig",
    "SyntheticSequence",
    "SequenceJob",
    "clothing_texture",
    "dataset_plan",
    "generate_dataset",
    "person_motion",
    "render_sequence",
    "sample_scene",
    "scene_for_job",
    "held_out_scene",
]
