"""A bag whose writer was killed: readable as it is, and made a normal indexed bag again."""

import shutil
import subprocess
import sys

import pytest
from train_core.bagio import BagError, BagWriter, read_bag, repair_bag


def _killed_bag(tmp_path, n=50, flushed=40, old_writer=True):
    """A bag as ``kill -9`` leaves it: ``flushed`` messages on disk, no summary. The writer's
    bag ends in a provisional footer and has metadata.yaml; ``old_writer``: neither (a writer
    without provisional footer and early metadata, or a tail cut mid-record)."""
    bag = tmp_path / "bag"
    w = BagWriter(bag, namespace="/rec")
    for s in range(n):
        w.write("odometer", 100.0 + 0.1 * s, {"seq": s, "distance": 1.0 * s, "speed": 2.0,
                                               "speed_variance": 0.01})
        w.write("control", 100.0 + 0.1 * s, {"target_acceleration": 0.1 * s})
        if s == flushed - 1:
            w.flush()
            snap = tmp_path / "snap"
            shutil.copytree(bag, snap)  # the files at the moment of the kill
    w.close()
    shutil.rmtree(bag)
    snap.rename(bag)
    if old_writer:
        from train_core.bagio import PROVISIONAL_TAIL

        (bag / "metadata.yaml").unlink()
        (mcap,) = bag.glob("*.mcap")
        with open(mcap, "r+b") as fh:
            fh.truncate(mcap.stat().st_size - len(PROVISIONAL_TAIL))
    return bag


def _readers_agree(bag, n):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as r:
        got = [(c.topic, t) for c, t, _ in r.messages()]
    assert len(got) == 2 * n
    (mcap,) = bag.glob("*.mcap")
    with open(mcap, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary() is not None
        msgs = list(reader.iter_messages())
    assert len(msgs) == 2 * n


def test_killed_bag_opens_as_it_is_in_every_reader(tmp_path):
    """The writer keeps metadata.yaml and a provisional footer on disk at every flush."""
    bag = _killed_bag(tmp_path, old_writer=False)
    assert (bag / "metadata.yaml").exists()
    rec = read_bag(bag)
    assert [f["seq"] for _, _, f in rec.topics["odometer"]] == list(range(40))
    assert "not closed" in rec.skipped["(file tail)"]
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as r:
        assert len(list(r.messages())) == 80
    (mcap,) = bag.glob("*.mcap")
    with open(mcap, "rb") as fh:
        assert len(list(make_reader(fh).iter_messages())) == 80
    assert repair_bag(bag) == bag  # indexed now
    _readers_agree(bag, 40)
    assert read_bag(bag).topics == rec.topics and read_bag(bag).skipped == {}


def test_killed_old_bag_mcap_file_is_refused_by_the_mcap_reader(tmp_path):
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    bag = _killed_bag(tmp_path)
    (mcap,) = bag.glob("*.mcap")
    with open(mcap, "rb") as fh, pytest.raises(McapError):
        list(make_reader(fh).iter_messages())


def test_killed_old_bag_is_refused_by_the_readers_then_repaired(tmp_path):
    from rosbags.highlevel import AnyReader, AnyReaderError

    bag = _killed_bag(tmp_path)
    with pytest.raises((AnyReaderError, FileNotFoundError)):  # no metadata.yaml
        with AnyReader([bag]):
            pass
    before = read_bag(bag)  # the recovery path
    assert [f["seq"] for _, _, f in before.topics["odometer"]] == list(range(40))
    assert repair_bag(bag) == bag
    assert (bag / "metadata.yaml").exists()
    assert (tmp_path / "bag.broken").is_dir()
    _readers_agree(bag, 40)
    after = read_bag(bag)
    assert after.topics == before.topics and after.namespace == "/rec"
    with pytest.raises(BagError):
        repair_bag(bag)  # a normal bag: nothing to repair


def test_repair_command_line(tmp_path):
    bag = _killed_bag(tmp_path, n=20, flushed=10)
    res = subprocess.run([sys.executable, "-m", "train_core.bagio", "repair", str(bag),
                          "--delete-broken"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "20 messages" in res.stdout
    assert not (tmp_path / "bag.broken").exists()
    _readers_agree(bag, 10)
    res = subprocess.run([sys.executable, "-m", "train_core.bagio", "repair", str(bag)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "nothing to repair" in res.stderr


def test_a_closed_bag_without_its_metadata_is_read_and_not_called_unclosed(tmp_path):
    """A bag copied without metadata.yaml: its .mcap is complete (summary and footer)."""
    bag = tmp_path / "bag"
    with BagWriter(bag) as w:
        for s in range(20):
            w.write("odometer", 1.0 + 0.1 * s, {"seq": s, "distance": 1.0 * s, "speed": 2.0,
                                                 "speed_variance": 0.01})
    (bag / "metadata.yaml").unlink()
    rec = read_bag(bag)
    assert [f["seq"] for _, _, f in rec.topics["odometer"]] == list(range(20))
    note = rec.skipped["(file tail)"]
    assert "no metadata.yaml; the .mcap files are complete" in note and "not closed" not in note
