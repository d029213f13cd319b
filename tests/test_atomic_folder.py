"""train/atomic_folder.py: a folder written atomically, and a cached folder keyed by its settings that is made once
and never overwritten (the VQA set and the grounding scenes both use it)."""

import json

import pytest

from trivla_drake.train.atomic_folder import atomic_folder, ensure_cached_folder


def _maker(folder, settings, made):
    def make():
        made.append(folder)
        with atomic_folder(folder) as tmp:
            (tmp / "meta.json").write_text(json.dumps(settings))
        return folder
    return make


def test_a_cached_folder_is_made_once_and_refuses_other_settings_other_contents_and_a_broken_meta(tmp_path):
    settings, made = {"scenes": 2, "seed": 0}, []
    folder = tmp_path / "set"
    assert ensure_cached_folder(folder, settings, _maker(folder, settings, made), what="things") == folder
    assert ensure_cached_folder(folder, settings, _maker(folder, settings, made), what="things") == folder
    assert made == [folder]  # reused the second time
    with pytest.raises(ValueError, match=r"holds things made with other settings \(scenes: 2 there, 3 asked\)"):
        ensure_cached_folder(folder, {**settings, "scenes": 3}, _maker(folder, settings, made), what="things")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "mine.txt").write_text("keep")
    with pytest.raises(ValueError, match="not empty and does not hold things"):
        ensure_cached_folder(tmp_path / "other", settings, _maker(tmp_path / "other", settings, made), what="things")
    assert (tmp_path / "other" / "mine.txt").read_text() == "keep"
    (folder / "meta.json").write_text("{broken")
    with pytest.raises(ValueError, match="meta.json is not valid JSON .*delete .* to make the things again"):
        ensure_cached_folder(folder, settings, _maker(folder, settings, made), what="things")
    assert made == [folder] and (folder / "meta.json").read_text() == "{broken"  # nothing was overwritten


def test_a_failed_atomic_write_leaves_the_old_folder_as_it_was(tmp_path):
    folder = tmp_path / "set"
    with atomic_folder(folder) as tmp:
        (tmp / "a.txt").write_text("first")
    with pytest.raises(RuntimeError, match="died"):
        with atomic_folder(folder) as tmp:
            (tmp / "a.txt").write_text("second")
            raise RuntimeError("died")
    assert (folder / "a.txt").read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["set"]


def test_a_replaced_folder_leaves_no_set_aside_copy(tmp_path):
    """The old folder is set aside (not deleted) until the new one is in place, then removed."""
    folder = tmp_path / "f"
    for text in ("old", "new"):
        with atomic_folder(folder) as tmp:
            (tmp / "x.txt").write_text(text)
    assert (folder / "x.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]
