"""davis_rig.scene.mocap.splits: the deterministic 47/13 split by trial."""

import pytest

from davis_rig.scene.mocap.splits import (
    PAPER_TEST_TRIALS,
    PAPER_TRAIN_TRIALS,
    find_trials,
    split_trials,
    trial_id,
)


@pytest.fixture()
def cmu_folder(tmp_path):
    root = tmp_path / "CMU"
    for subject in range(1, 7):
        folder = root / f"{subject:02d}"
        folder.mkdir(parents=True)
        for trial in range(1, 11):
            (folder / f"{subject:02d}_{trial:02d}_poses.npz").write_bytes(b"")
        (folder / "shape.npz").write_bytes(b"")  # not a trial
    return root


def test_find_trials(cmu_folder):
    trials = find_trials(cmu_folder)
    assert len(trials) == 60 and list(trials) == sorted(trials)
    assert trial_id(trials["03/03_07"]) == "03/03_07"
    assert list(find_trials(cmu_folder, subjects=["02"])) == [f"02/02_{k:02d}" for k in range(1, 11)]
    with pytest.raises(FileNotFoundError):
        find_trials(cmu_folder / "nope")


def test_paper_counts_disjoint_and_deterministic(cmu_folder):
    trials = find_trials(cmu_folder)
    split = split_trials(trials)
    assert (len(split.train), len(split.test)) == (PAPER_TRAIN_TRIALS, PAPER_TEST_TRIALS)
    assert not set(split.train) & set(split.test) and set(split.train) | set(split.test) == set(trials)
    assert split.test_paths()[0] == trials[split.test[0]]
    # independent of the order and form of the input (ids, paths, dict)
    assert split_trials(list(reversed(list(trials)))).test == split.test
    assert split_trials(list(trials.values())).test == split.test
    # the salt is the only knob of the ranking
    assert split_trials(trials, salt="other").test != split.test


def test_split_by_subject_and_errors(cmu_folder):
    trials = find_trials(cmu_folder)
    split = split_trials(trials, n_test=2, by="subject")
    test_subjects = {t.split("/")[0] for t in split.test}
    assert len(test_subjects) == 2 and len(split.test) == 20
    assert not test_subjects & {t.split("/")[0] for t in split.train}
    assert split_trials(["a/1", "a/2", "b/1"], n_test=0).test == ()
    with pytest.raises(ValueError):
        split_trials(["a/1", "a/1"])
    with pytest.raises(ValueError):
        split_trials(["a/1"], n_test=2)
    with pytest.raises(ValueError):
        split_trials(["a/1"], by="session")


def test_bvh_trials_get_the_amass_ids_and_split(cmu_folder, tmp_path):
    """CMU BVH files ``<subject>/<subject>_<trial>.bvh``: same trial ids, hence the same split, as AMASS."""
    amass = find_trials(cmu_folder)
    root = tmp_path / "cmu_bvh"
    for tid in amass:
        subject, stem = tid.split("/")
        (root / subject).mkdir(parents=True, exist_ok=True)
        (root / subject / f"{stem}.bvh").write_bytes(b"")
    (root / "01" / "01_01.txt").write_bytes(b"")  # not a trial
    bvh = find_trials(root, pattern="*.bvh")
    assert list(bvh) == list(amass) and trial_id(bvh["03/03_07"]) == "03/03_07"
    split = split_trials(bvh)
    assert split.test == split_trials(amass).test and split.test_paths()[0].suffix == ".bvh"
    by_name = split_trials([str(p) for p in bvh.values()])  # strings ending in .bvh are file paths
    assert by_name.test == split.test and by_name.paths == split.paths
