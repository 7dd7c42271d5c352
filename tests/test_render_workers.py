"""Render workers draw a share of each video's frames in another process: the frames must be those
this process would draw, and a worker that fails must cost nothing but time."""
import json
import socket
import time

import numpy as np
import pytest

from salad.render import last_render_stats, render_frames, render_side_by_side, video, workers
from salad.render.worker_main import scene_from_message
from tests.conftest import synthetic_walk

SIZE = (128, 128)


@pytest.fixture(scope="module")
def walk():
    return synthetic_walk(40, turn=0.4)


@pytest.fixture
def no_workers():
    workers.stop()
    yield
    workers.stop()


def ready_worker() -> workers.Worker:
    workers.start(1)
    workers.wait_ready()
    return workers.running()[0]


def single(walk, **kw):
    n = len(walk)
    tint = np.linspace(0.0, 1.0, n * 22).reshape(n, 22)
    mask = np.zeros((n, 22), bool)
    mask[::5, 0] = True
    return render_frames(walk, size=SIZE, title="a person walks", tint=tint, targets=walk + 0.1, target_mask=mask,
                         trajectory=walk[:, 0], antialias=False, **kw)


def test_a_worker_draws_the_frames_this_process_would(walk, tmp_path, no_workers):
    alone = single(walk)
    assert last_render_stats()["worker_frames"] == 0
    video.panel_cache.clear()
    ref = render_side_by_side([walk, walk[:25]], ["source", "edited"], tmp_path / "alone.mp4", size=SIZE).read_bytes()

    ready_worker()
    shared = single(walk)
    assert 0 < last_render_stats()["worker_frames"] < len(walk), "the worker drew a share, this process the rest"
    np.testing.assert_array_equal(shared, alone)
    # side by side, antialiased, panels of different lengths (the shorter one holds its last frame)
    video.panel_cache.clear()
    out = render_side_by_side([walk, walk[:25]], ["source", "edited"], tmp_path / "shared.mp4", size=SIZE)
    assert last_render_stats()["worker_frames"] > 0
    assert out.read_bytes() == ref
    # the panels the worker drew went into the cache as this process's would: the next edit reuses the source
    render_side_by_side([walk, walk[:30]], ["source", "edited"], tmp_path / "next.mp4", size=SIZE)
    assert last_render_stats()["reused_panels"] == 1


def test_a_worker_that_dies_costs_only_time(walk, no_workers):
    alone = single(walk)
    worker = ready_worker()

    def kill(done, total):
        if worker.process.poll() is None:
            worker.process.kill()
            worker.process.wait()

    np.testing.assert_array_equal(single(walk, progress=kill), alone)
    assert last_render_stats()["worker_frames"] < len(walk)
    deadline = time.monotonic() + 30        # its reader thread notices the closed socket
    while worker.idle and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not worker.idle
    with pytest.raises(RuntimeError, match="exited"):
        workers.wait_ready()
    np.testing.assert_array_equal(single(walk), alone)        # without it
    assert last_render_stats()["worker_frames"] == 0
    assert ready_worker() is not worker and workers.running()[0].idle, "start() replaces a dead worker"


def test_short_renders_and_no_workers_stay_in_this_process(walk, no_workers):
    single(walk[:workers.MIN_SHARED_FRAMES - 1])
    assert last_render_stats()["worker_frames"] == 0
    ready_worker()
    single(walk[:workers.MIN_SHARED_FRAMES - 1])
    assert last_render_stats()["worker_frames"] == 0
    with pytest.raises(ValueError, match="render workers"):
        workers.start(-1)


def test_scenes_travel_as_json_and_raw_arrays(walk):
    scene = video.Scene([walk], (64, 48), 20.0, title="a person walks", tint=np.zeros((len(walk), 22)),
                        target_mask=np.ones((len(walk), 22), bool), targets=walk, cmap="attention")
    header, arrays = workers.scene_message(scene)
    ours, theirs = socket.socketpair()
    with ours, theirs:
        workers.send_message(ours, {"scene": header}, arrays)
        got, back = workers.recv_message(theirs)
    again = scene_from_message(json.loads(json.dumps(got["scene"])), back)
    assert again.size == (64, 48) and again.title == "a person walks" and again.labels is None
    assert again.trajectory is None and again.target_mask.dtype == bool
    for name in ("tint", "targets", "target_mask"):
        np.testing.assert_array_equal(getattr(again, name), getattr(scene, name))
    np.testing.assert_array_equal(again.motions[0], walk)
    ours, theirs = socket.socketpair()
    with ours, theirs, pytest.raises(ValueError, match="refusing"):
        ours.sendall(workers._HEADER.pack(len(b'{"arrays": [["|O", [1]]]}')) + b'{"arrays": [["|O", [1]]]}')
        workers.recv_message(theirs)
    pair = video.Scene([walk, walk[:5]], (64, 64), 20.0, labels=["a", "b"])
    back = scene_from_message(*workers.scene_message(pair))
    assert back.labels == ["a", "b"] and [len(m) for m in back.motions] == [len(walk), 5]


def test_a_worker_that_cannot_draw_says_why_and_this_process_draws(walk, no_workers, monkeypatch, caplog):
    alone = single(walk)
    worker = ready_worker()
    real = workers.scene_message

    def unknown_colour_map(scene):
        header, arrays = real(scene)
        return dict(header, cmap="no-such-map"), arrays

    monkeypatch.setattr(workers, "scene_message", unknown_colour_map)
    with caplog.at_level("WARNING", logger="salad.render"):
        np.testing.assert_array_equal(single(walk), alone)
    assert last_render_stats()["worker_frames"] == 0
    assert "no-such-map" in caplog.text
    assert worker.idle, "the worker stays ready for the next render"
