"""A corrupt newest checkpoint is moved aside (never deleted) and the next newest restored; a checkpoint that is
intact but shaped for another run is refused at once and nothing moves (`learner.checkpoint`)."""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.learner.checkpoint import Checkpointer, CheckpointError, CorruptCheckpointError
from tests.support.checkpoint_damage import largest_file, truncate


@pytest.fixture(scope="module", autouse=True)
def frozen_heap():
    """What earlier tests left on the heap is frozen (`gc.freeze`) while these tests run, so the collections below
    walk only the objects these tests make: late in a full run the heap holds millions of objects, and a full
    collection after every test took seconds each."""
    gc.freeze()
    yield
    gc.unfreeze()


@pytest.fixture(autouse=True)
def collect_abandoned_reads(frozen_heap):
    """Orbax abandons an item's other reads when one fails, and they report 'Exception ignored' when collected:
    collected here, inside each test, any report that `restore` let through shows as a warning of that test."""
    yield
    gc.collect()


SIZE = 4096  # random float32s: incompressible, so orbax writes them to a data file of their own (not inlined)


def train_tree(step: int) -> dict:
    rng = np.random.default_rng(step)
    return {"params": {"w": rng.standard_normal(SIZE).astype(np.float32)}, "version": np.array(step, np.int32)}


TEMPLATE = train_tree(0)


def write_steps(directory: Path, steps=(1, 2, 3)) -> None:
    with Checkpointer(directory) as checkpoints:
        for step in steps:
            checkpoints.save(step, {"train": train_tree(step)}, {"update": step}, f"step = {step}\n")


def truncate_data_file(step_dir: Path) -> str:
    data = largest_file(step_dir / "train")
    assert data.stat().st_size > SIZE * 4 // 2 and "ocdbt" in str(data.parent.parent), data  # the arrays' bytes
    truncate(data)
    return "its train item"


def truncate_counters(step_dir: Path) -> str:
    truncate(step_dir / "counters" / "metadata")
    return "its counters item"


def empty_train_item(step_dir: Path) -> str:
    for entry in (step_dir / "train").iterdir():
        shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    return "its train item"


def remove_train_item(step_dir: Path) -> str:
    shutil.rmtree(step_dir / "train")
    return "its train item"


def truncate_tree_metadata(step_dir: Path) -> str:
    truncate(step_dir / "train" / "manifest.ocdbt")  # the OCDBT root: no array's shape can be read
    return "its train item"


def garble_config(step_dir: Path) -> str:
    (step_dir / "config" / "metadata").write_text('{"toml": 3}')
    return "its config item"


def empty_step(step_dir: Path) -> str:
    for entry in step_dir.iterdir():
        shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    (step_dir / "README").write_text("a stray file: the directory must be moved with it")
    return "its directory"


def snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in directory.rglob("*") if p.is_file()}


@pytest.mark.parametrize("corrupt", [truncate_data_file, truncate_counters, empty_train_item, remove_train_item,
                                     truncate_tree_metadata, garble_config, empty_step])
def test_a_corrupt_newest_checkpoint_is_moved_aside_and_the_previous_one_restored(
    tmp_path, caplog, corrupt: Callable[[Path], str]
):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    phrase = corrupt(directory / "3")
    damaged = snapshot(directory / "3")
    caplog.set_level(logging.WARNING, logger="impulse.learner.checkpoint")
    with Checkpointer(directory) as checkpoints:
        restored = checkpoints.restore({"train": TEMPLATE})
        assert restored.step == 2 and restored.counters == {"update": 2} and restored.config_toml == "step = 2\n"
        np.testing.assert_array_equal(restored.items["train"]["params"]["w"], train_tree(2)["params"]["w"])
        assert checkpoints.all_steps() == [1, 2] and checkpoints.latest_step() == 2
    moved = tmp_path / "checkpoints-corrupt" / "3"
    assert not (directory / "3").exists()
    assert snapshot(moved) == damaged, "the corrupt checkpoint is kept as it was, every file"
    warning = next(r.getMessage() for r in caplog.records if r.name == "impulse.learner.checkpoint")
    assert "checkpoint 3 is corrupt: " + phrase in warning and str(moved) in warning


def test_a_reader_skips_a_corrupt_newest_checkpoint_and_leaves_it_in_place(tmp_path, caplog):
    """`set_aside=False` (evaluation, export, a shipped agent loaded to play): the previous checkpoint is restored
    and the corrupt one stays where it was, every file, with no `-corrupt` folder made."""
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    truncate_data_file(directory / "3")
    damaged = snapshot(directory / "3")
    caplog.set_level(logging.WARNING, logger="impulse.learner.checkpoint")
    with Checkpointer(directory) as checkpoints:
        restored = checkpoints.restore({"train": TEMPLATE}, set_aside=False)
        assert restored.step == 2 and restored.counters == {"update": 2}
        assert checkpoints.all_steps() == [1, 2, 3]
    assert snapshot(directory / "3") == damaged and not (tmp_path / "checkpoints-corrupt").exists()
    assert any("checkpoint 3 is corrupt" in r.getMessage() and "left in place" in r.getMessage()
               for r in caplog.records)


def test_every_checkpoint_corrupt_is_an_error_that_names_the_directory_and_each_problem(tmp_path):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    for step in (1, 2, 3):
        truncate_counters(directory / str(step))
    with Checkpointer(directory) as checkpoints, pytest.raises(CheckpointError) as caught:
        checkpoints.restore({"train": TEMPLATE})
    message = str(caught.value)
    assert f"no usable checkpoint in {directory}" in message
    for step in (1, 2, 3):
        assert f"checkpoint {step}: its counters item ({directory / str(step) / 'counters' / 'metadata'})" in message
        assert (tmp_path / "checkpoints-corrupt" / str(step) / "counters" / "metadata").is_file()


@pytest.mark.parametrize("template", [
    {"params": {"w": np.zeros(SIZE + 1, np.float32)}, "version": np.array(0, np.int32)},  # other sizes
    {"params": {"w": np.zeros(SIZE, np.float32), "b": np.zeros(3, np.float32)}, "version": np.array(0, np.int32)},
], ids=["shape", "structure"])
def test_a_checkpoint_of_another_network_is_a_mismatch_and_nothing_moves(tmp_path, template):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    before = snapshot(directory)
    with Checkpointer(directory) as checkpoints:
        with pytest.raises(CheckpointError, match="different network, sizes or number of environments") as caught:
            checkpoints.restore({"train": template})
        assert not isinstance(caught.value, CorruptCheckpointError)
        assert "checkpoint 3" in str(caught.value) and "params/" in str(caught.value)
        assert checkpoints.all_steps() == [1, 2, 3]
    assert not (tmp_path / "checkpoints-corrupt").exists()
    assert snapshot(directory) == before


def test_a_mismatch_behind_a_corrupt_checkpoint_stops_the_fallback(tmp_path):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    truncate_counters(directory / "3")
    other = {"params": {"w": np.zeros(8, np.float32)}, "version": np.array(0, np.int32)}
    with Checkpointer(directory) as checkpoints, pytest.raises(CheckpointError, match="different network"):
        checkpoints.restore({"train": other})
    assert sorted(p.name for p in directory.iterdir() if p.name.isdigit()) == ["1", "2"]
    assert (tmp_path / "checkpoints-corrupt" / "3").is_dir()


def test_the_moved_step_number_can_be_written_again_and_moved_again(tmp_path):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    truncate_data_file(directory / "3")
    with Checkpointer(directory) as checkpoints:
        assert checkpoints.restore({"train": TEMPLATE}).step == 2
        checkpoints.save(3, {"train": train_tree(30)}, {"update": 3}, "again = true\n")
        checkpoints.wait()
        again = checkpoints.restore({"train": TEMPLATE})
        assert again.step == 3 and again.config_toml == "again = true\n"
        np.testing.assert_array_equal(again.items["train"]["params"]["w"], train_tree(30)["params"]["w"])
    truncate_counters(directory / "3")
    with Checkpointer(directory) as checkpoints:
        assert checkpoints.restore({"train": TEMPLATE}).step == 2
    aside = tmp_path / "checkpoints-corrupt"
    assert (aside / "3").is_dir(), "the first corrupt step 3 is still there"
    assert json.loads((aside / "3-2" / "config" / "metadata").read_text()) == {"toml": "again = true\n"}


def test_a_corrupt_checkpoint_asked_for_by_step_is_an_error_and_stays(tmp_path):
    directory = tmp_path / "checkpoints"
    write_steps(directory)
    truncate_data_file(directory / "3")
    with Checkpointer(directory) as checkpoints:
        with pytest.raises(CorruptCheckpointError, match=r"checkpoint 3 .* train item .*left in place") as caught:
            checkpoints.restore({"train": TEMPLATE}, step=3)
        assert caught.value.step == 3 and caught.value.item == "train"
        assert checkpoints.items_at(3) == {"train"}
        with pytest.raises(CheckpointError, match="no checkpoint 7"):
            checkpoints.restore({"train": TEMPLATE}, step=7)
        assert checkpoints.all_steps() == [1, 2, 3]
    assert not (tmp_path / "checkpoints-corrupt").exists()


def test_templates_are_chosen_for_each_checkpoint_tried(tmp_path):
    directory = tmp_path / "checkpoints"
    envs = {"key": np.array([1, 2], np.uint32)}
    with Checkpointer(directory) as checkpoints:
        checkpoints.save(1, {"train": train_tree(1)}, {"update": 1}, "")  # a policy alone (imported)
        checkpoints.save(2, {"train": train_tree(2), "envs": envs}, {"update": 2}, "")
    truncate_counters(directory / "2")
    held: list[frozenset[str]] = []

    def choose(items: frozenset[str]) -> dict:
        held.append(items)
        return {"train": TEMPLATE} if items == {"train"} else {"train": TEMPLATE, "envs": envs}

    with Checkpointer(directory) as checkpoints:
        restored = checkpoints.restore(choose)
    assert held == [frozenset({"train", "envs"}), frozenset({"train"})]
    assert restored.step == 1 and set(restored.items) == {"train"}


def test_a_lost_item_directory_is_corruption_not_a_smaller_checkpoint(tmp_path):
    # A fused run that finds only `train` would go on with the policy alone on fresh environments: a checkpoint
    # whose own metadata lists `envs` but has lost its directory must be treated as corrupt instead.
    directory = tmp_path / "checkpoints"
    envs = {"key": np.array([1, 2], np.uint32)}
    with Checkpointer(directory) as checkpoints:
        for step in (1, 2):
            checkpoints.save(step, {"train": train_tree(step), "envs": envs}, {"update": step}, "")
    shutil.rmtree(directory / "2" / "envs")

    def choose(items: frozenset[str]) -> dict:
        return {"train": TEMPLATE} if items == {"train"} else {"train": TEMPLATE, "envs": envs}

    with Checkpointer(directory) as checkpoints:
        restored = checkpoints.restore(choose)
    assert restored.step == 1 and set(restored.items) == {"train", "envs"}
    assert (tmp_path / "checkpoints-corrupt" / "2" / "train").is_dir()


def test_a_truncated_data_file_restored_onto_the_device_is_corruption_too_and_quiet(tmp_path):
    # Restoring into device arrays (the learner's templates) orbax wraps the read error in a bare Exception, and
    # abandons the reads of the item's other arrays, which would each print an 'Exception ignored' traceback.
    directory = tmp_path / "checkpoints"
    rng = np.random.default_rng(0)
    with Checkpointer(directory) as checkpoints:
        for step in (1, 2):
            tree = {f"w{i}": rng.standard_normal(4096).astype(np.float32) for i in range(64)}
            checkpoints.save(step, {"train": tree}, {"update": step}, "")
    data = max((p for p in (directory / "2" / "train").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    data.write_bytes(data.read_bytes()[:1000])  # the first array or so is there, the rest lost
    template = jax.tree.map(jnp.zeros_like, tree)
    reports: list[str] = []
    previous, sys.unraisablehook = sys.unraisablehook, lambda unraisable: reports.append(repr(unraisable.exc_value))
    try:
        with Checkpointer(directory) as checkpoints:
            restored = checkpoints.restore({"train": template})
        time.sleep(0.2)
        gc.collect()
    finally:
        sys.unraisablehook = previous
    assert reports == [], "orbax's abandoned reads are not reported after the warning that says it all"
    assert restored.step == 1 and isinstance(restored.items["train"]["w0"], jax.Array)
    assert (tmp_path / "checkpoints-corrupt" / "2" / "train").is_dir()


def test_a_task_of_an_abandoned_read_collected_later_is_not_reported_but_other_tasks_are(caplog):
    # The garbage collector may reach an abandoned read's task after the restore has returned; asyncio then logs
    # 'Task exception was never retrieved' with a traceback. That one report is dropped, any other kept.
    async def fail(message: str) -> None:
        raise Exception(message)

    caplog.set_level(logging.ERROR, logger="asyncio")
    for message in ("Encountered error while reading array index: (slice(0, 8, 1),)", "a real bug"):
        loop = asyncio.new_event_loop()
        task = loop.create_task(fail(message))
        loop.run_until_complete(asyncio.sleep(0))
        loop.close()
        del task
        gc.collect()
    reports = [r.getMessage() + str(r.exc_info[1]) for r in caplog.records if r.name == "asyncio"]
    assert len(reports) == 1 and "a real bug" in reports[0], reports


def test_a_checkpoint_that_fails_to_write_costs_itself_alone(tmp_path, caplog):
    """A background write that fails (here: its temporary directory removed while orbax writes it) is logged and
    counted at the next save, which goes on and lands; the checkpoint before it stays intact."""
    tree = {"w": jnp.ones((2048, 4096))}  # 32 MB: written long enough for the fault to land mid-write
    checkpoints = Checkpointer(tmp_path / "checkpoints")
    checkpoints.save(1, {"train": tree}, {"updates": 1}, "x = 1")
    checkpoints.wait()
    interrupted = None
    for step in range(2, 7):
        checkpoints.save(step, {"train": tree}, {"updates": step}, "x = 1")
        writing = tmp_path / "checkpoints" / f"{step}.orbax-checkpoint-tmp"
        deadline = time.monotonic() + 5
        while not writing.exists() and not (tmp_path / "checkpoints" / str(step)).exists() \
                and time.monotonic() < deadline:
            time.sleep(0.001)
        if writing.exists():
            interrupted = step
            until = time.monotonic() + 1.0  # orbax may create parts again after one removal: keep removing them
            while time.monotonic() < until:
                shutil.rmtree(writing, ignore_errors=True)
                time.sleep(0.01)
            break
        checkpoints.wait()
    assert interrupted is not None, "every write finished before the fault could land"
    with caplog.at_level(logging.ERROR, logger="impulse.learner.checkpoint"):
        checkpoints.save(10, {"train": tree}, {"updates": 10}, "x = 1")
        checkpoints.wait()
    assert checkpoints.failed_saves == 1 and "failed to write in the background" in caplog.text
    assert interrupted not in checkpoints.all_steps() and {1, 10} <= set(checkpoints.all_steps())
    restored = checkpoints.restore({"train": tree})
    assert restored.step == 10 and restored.counters == {"updates": 10}
    checkpoints.close()
