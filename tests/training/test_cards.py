"""The model card states the recipe the run used (losses, sampling, stream augmentation), not a fixed text."""

from __future__ import annotations

from davis_rig.training.cards import render_model_card


def _card(**train_config) -> str:
    return render_model_card(model_name="m", model_config={"name": "RVT-mini"}, train_config=train_config,
                             dataset_card=None, validation=None)


def test_recipe_text_follows_the_train_config():
    mixed = _card(use_l1=False, sampling="mixed", stream_augment={"flip_prob": 0.5})
    assert "no L1" in mixed and "carried from chunk to chunk" in mixed and '{"flip_prob": 0.5}' in mixed
    random_l1 = _card(use_l1=True, sampling="random", stream_augment={"flip_prob": 0.5})
    assert "+ L1)" in random_l1 and "no L1" not in random_l1
    assert "random chunks, states reset per chunk" in random_l1 and "carried from chunk" not in random_l1
    assert "stream augmentation" not in random_l1  # no streaming lanes in random sampling
    assert "L1 not recorded" in _card() and "sampling: not recorded" in _card()
