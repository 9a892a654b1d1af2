import pytest

from uevavd.data import splits


def test_counts_match_the_paper():
    assert splits.counts() == {
        "train": {"contexts": 100, "views": 60500},
        "simple": {"contexts": 25, "views": 15125},
        "hard": {"contexts": 25, "views": 15125},
    }


def test_block_structure_with_the_typos_corrected():
    train = splits.contexts("train")
    assert train[:20] == tuple(range(1, 21))
    assert set(range(121, 141)) <= set(train) and 120 not in train  # paper prints "120, ..., 140"
    hard = splits.contexts("hard")
    assert set(range(56, 61)) <= set(hard) and 61 not in hard  # paper prints "56, ..., 80"
    assert splits.contexts("simple")[:5] == (21, 22, 23, 24, 25)
    assert splits.contexts("test") == tuple(sorted(splits.contexts("simple") + hard))
    assert [splits.block_of(c) for c in (1, 30, 31, 150)] == [0, 0, 1, 4]


def test_splits_partition_the_contexts():
    all_ids = set()
    for s in splits.SPLITS:
        ids = set(splits.contexts(s))
        assert not ids & all_ids
        all_ids |= ids
    assert all_ids == set(range(1, 151))


def test_bad_ids_and_names():
    for bad in (0, 151, 2.5, "x"):
        with pytest.raises(ValueError, match="context id"):
            splits.split_of(bad)
    with pytest.raises(ValueError, match="unknown split 'hardd'"):
        splits.contexts("hardd")


def test_subset_keeps_blocks():
    ids = splits.subset({"train": 4, "simple": 1, "hard": 1})
    assert len(ids) == 30
    assert [splits.split_of(c) for c in ids[:6]] == ["train"] * 4 + ["simple", "hard"]
    assert ids[:6] == (1, 2, 3, 4, 21, 26)
    with pytest.raises(ValueError, match="hard=6"):
        splits.subset({"hard": 6})
