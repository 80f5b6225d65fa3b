"""Frame sources on real files read by real OpenCV: replay, corrupt frames, a capture that vanishes."""
from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.capture.replay import open_recording, replay_source
from companion.capture.source import Backoff, LatestFrame, SourceError
from companion.capture.v4l2 import CaptureSource, v4l2_source
from companion.types import Frame

PERIOD_NS = 20_000_000  # 50 fps keeps the real-time tests short


def image_with_number(n: int, size=(48, 64)) -> np.ndarray:
    """A frame whose mean gray level encodes n (readable back after MJPG too)."""
    return np.full(size, 10 + 8 * n, dtype=np.uint8)


def number_of(image: np.ndarray) -> int:
    return int(round((float(image.mean()) - 10) / 8))


def write_sequence(folder: Path, count: int, period_ns: int = PERIOD_NS, jitter=None) -> Path:
    (folder / "frames").mkdir(parents=True)
    t = 0
    lines = ["frame,t_ns,file"]
    for n in range(count):
        name = f"frames/{n:06d}.png"
        cv2.imwrite(str(folder / name), image_with_number(n))
        lines.append(f"{n},{t},{name}")
        t += period_ns + (jitter[n] if jitter is not None else 0)
    (folder / "timestamps.csv").write_text("\n".join(lines) + "\n")
    return folder


def write_video(path: Path, count: int, fps: float = 25.0, numbers: list[int] | None = None) -> Path:
    """An MJPG video of frames 0..count-1, or of ``numbers`` (a number again is the very same image)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48), isColor=False)
    assert writer.isOpened()
    for n in (range(count) if numbers is None else numbers):
        writer.write(image_with_number(n))
    writer.release()
    return path


def drain(source, limit_s: float = 10.0) -> list[Frame]:
    frames = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        frame = source.get(timeout_s=0.1)
        if frame is not None:
            frames.append(frame)
        elif source.finished:
            break
    return frames


def test_sequence_folder_is_read_with_its_timestamps(tmp_path):
    jitter = [0, 3_000_000, -2_000_000, 0, 5_000_000, 0]
    rec = open_recording(write_sequence(tmp_path / "seq", 6, jitter=jitter))
    assert list(rec.frames) == list(range(6))
    assert list(np.diff(rec.t_ns)) == [PERIOD_NS + j for j in jitter[:5]]
    assert rec.files[2].name == "000002.png" and rec.video is None


def test_realtime_replay_hands_frames_over_at_their_shifted_capture_time(tmp_path):
    jitter = [0, 4_000_000, 0, -3_000_000, 0, 0, 2_000_000, 0]
    source = replay_source(write_sequence(tmp_path / "seq", 8, jitter=jitter), realtime=True)
    source.start()
    received = []
    while len(received) < 8:
        frame = source.get(timeout_s=2.0)
        assert frame is not None
        received.append((frame, time.monotonic_ns()))
    source.close()
    rec = source.recording
    assert [number_of(f.image) for f, _ in received] == list(range(8))
    assert [f.index for f, _ in received] == list(range(8))
    # t_ns is the recorded time on the monotonic clock, and no frame arrives before it.
    assert [f.t_ns - source.clock_offset_ns for f, _ in received] == list(rec.t_ns)
    assert all(taken_ns >= f.t_ns for f, taken_ns in received)
    assert source.counters.captured == 8 and source.counters.dropped == 0


def test_fast_replay_delivers_every_frame_in_order_without_drops(tmp_path):
    source = replay_source(write_sequence(tmp_path / "seq", 30), realtime=False)
    source.start()
    frames = drain(source)
    source.close()
    assert [number_of(f.image) for f in frames] == list(range(30))
    # each frame keeps its recorded time, ahead of the clock (not the time it was read: time is not compressed)
    assert [f.t_ns - source.clock_offset_ns for f in frames] == list(open_recording(tmp_path / "seq").t_ns)
    assert source.counters.dropped == 0 and source.finished


def test_corrupt_missing_and_truncated_frames_are_skipped_and_counted(tmp_path):
    folder = write_sequence(tmp_path / "seq", 10)
    (folder / "frames/000002.png").write_bytes(b"not a png at all")
    data = (folder / "frames/000005.png").read_bytes()
    (folder / "frames/000005.png").write_bytes(data[: len(data) // 3])
    (folder / "frames/000007.png").unlink()
    source = replay_source(folder, realtime=False)
    source.start()
    frames = drain(source)
    source.close()
    assert [number_of(f.image) for f in frames] == [0, 1, 3, 4, 6, 8, 9]
    assert [f.index for f in frames] == [0, 1, 3, 4, 6, 8, 9]  # the recording's frame numbers
    assert source.counters.corrupt == 3


def test_newest_frame_wins_when_the_pipeline_is_slow(tmp_path):
    source = replay_source(write_sequence(tmp_path / "seq", 25), realtime=True)
    source.start()
    taken = []
    while True:
        frame = source.get(timeout_s=0.5)
        if frame is None:
            break
        taken.append(number_of(frame.image))
        time.sleep(3 * PERIOD_NS * 1e-9)  # a pipeline three frame periods slow
    source.close()
    assert taken == sorted(taken) and taken[-1] == 24
    assert source.counters.dropped > 0
    assert source.counters.captured == 25 == len(taken) + source.counters.dropped


def test_looping_replay_keeps_time_rising(tmp_path):
    source = replay_source(write_sequence(tmp_path / "seq", 4), realtime=True, loop=True)
    source.start()
    frames = [source.get(timeout_s=1.0) for _ in range(10)]
    source.close()
    assert [number_of(f.image) for f in frames] == [0, 1, 2, 3, 0, 1, 2, 3, 0, 1]
    assert [f.index for f in frames] == list(range(10))
    assert np.all(np.diff([f.t_ns for f in frames]) == PERIOD_NS)


def test_video_file_replay_spaces_frames_by_its_rate(tmp_path):
    video = write_video(tmp_path / "clip.avi", 12, fps=25.0)
    rec = open_recording(video)
    assert len(rec.frames) == 12 and rec.period_ns == 40_000_000
    source = replay_source(video, realtime=False)
    source.start()
    frames = drain(source)
    source.close()
    assert [number_of(f.image) for f in frames] == list(range(12))
    assert frames[0].image.shape == (48, 64) and frames[0].image.dtype == np.uint8


def test_sequence_folder_with_a_video_instead_of_frames(tmp_path):
    folder = tmp_path / "seq"
    folder.mkdir()
    write_video(folder / "video.avi", 5)
    (folder / "timestamps.csv").write_text("frame,t_ns,file\n" + "".join(f"{n},{n * 33_000_000},\n" for n in range(5)))
    rec = open_recording(folder)
    assert rec.video == folder / "video.avi" and rec.files is None
    source = replay_source(folder, realtime=False)
    source.start()
    assert [number_of(f.image) for f in drain(source)] == list(range(5))
    source.close()


def test_image_folder_needs_a_frame_rate(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    for n in range(3):
        cv2.imwrite(str(folder / f"img{n}.png"), image_with_number(n))
    with pytest.raises(SourceError, match="source.fps"):
        open_recording(folder)
    rec = open_recording(folder, fps=10)
    assert list(rec.t_ns) == [0, 100_000_000, 200_000_000]


@pytest.mark.parametrize("content, message", [
    ("frame,time,file\n0,0,a.png\n", "header lacks t_ns"),
    ("frame,t_ns,file\n0,0,a.png\n1,0,b.png\n", "must rise"),
    ("frame,t_ns,file\n0,zero,a.png\n", "integers"),
    ("frame,t_ns,file\n", "no frames"),
    ("frame,t_ns,file\n0,0,a.png\n1,1\n", "must name every frame"),
    (b"\xf0\x9f\x00\xc5 not text", "cannot read .*not a timestamps table"),
])
def test_bad_timestamps_name_the_file(tmp_path, content, message):
    """Every one a SourceError naming the file (a non-UTF-8 file was a bare 'utf-8 codec can't decode')."""
    if isinstance(content, bytes):
        (tmp_path / "timestamps.csv").write_bytes(content)
    else:
        (tmp_path / "timestamps.csv").write_text(content)
    with pytest.raises(SourceError, match=message) as error:
        open_recording(tmp_path)
    assert "timestamps.csv" in str(error.value)


def test_missing_path_is_named(tmp_path):
    with pytest.raises(SourceError, match="nowhere"):
        open_recording(tmp_path / "nowhere")


def test_latest_frame_mailbox_keeps_only_the_newest():
    box = LatestFrame()
    a, b = (Frame(np.zeros((2, 2), np.uint8), t, t) for t in (1, 2))
    assert box.put(a) is False and box.put(b) is True
    assert box.take(0.01) is b and box.take(0.01) is None
    box.close()
    assert box.take(5.0) is None  # returns at once when closed


class ConsumerPacedVideo:
    """Real cv2.VideoCaptures over a video file that hand a frame over only once the consumer took
    the previous one, as a camera's frame period would: a file reads far faster than a camera
    delivers, and the one-frame mailbox would drop frames whenever the consumer is slow (load)."""

    def __init__(self, path: Path):
        self.path = path
        self._turns = threading.Semaphore(1)  # frames that may be handed over before the next take
        self._stopped = threading.Event()

    def open(self) -> PacedCapture:
        return PacedCapture(cv2.VideoCapture(str(self.path)), self._wait_for_turn)

    def took(self, frame: Frame) -> Frame:
        """The consumer calls this for every frame it takes."""
        self._turns.release()
        return frame

    def stop(self) -> None:
        """No more consumer: a capture waiting for its turn gives up."""
        self._stopped.set()

    def _wait_for_turn(self) -> bool:
        while not self._turns.acquire(timeout=0.05):
            if self._stopped.is_set():
                return False
        return True


class PacedCapture:
    """The reading side of a cv2.VideoCapture whose grabbed frame waits for its turn;
    the end of the file needs no turn (nothing is handed over)."""

    def __init__(self, capture: cv2.VideoCapture, wait_for_turn):
        self._capture, self._wait_for_turn = capture, wait_for_turn

    def isOpened(self) -> bool:
        return self._capture.isOpened()

    def grab(self) -> bool:
        return self._capture.grab() and self._wait_for_turn()

    def retrieve(self):
        return self._capture.retrieve()

    def release(self) -> None:
        self._capture.release()


def test_capture_that_vanishes_is_reopened_with_backoff_and_resumes(tmp_path):
    """A real cv2.VideoCapture over a file: its end is a camera that stops delivering,
    its removal a device that vanished; frames resume when it is back."""
    video = ConsumerPacedVideo(write_video(tmp_path / "cam.avi", 5))
    hidden = tmp_path / "cam.hidden"
    source = CaptureSource(video.open, name="test",
                           stall_timeout_s=0.15, backoff_initial_s=0.05, backoff_max_s=0.2)
    source.start()
    first = drain_until(source, count=5, took=video.took)
    video.path.rename(hidden)  # the device goes away after its first 5 frames
    deadline = time.monotonic() + 5
    while source.counters.reopens < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    reopens_while_gone = source.counters.reopens
    hidden.rename(video.path)  # and comes back
    second = drain_until(source, count=5, took=video.took)
    video.stop()
    source.close()
    assert [number_of(f.image) for f in first] == list(range(5))
    assert [number_of(f.image) for f in second] == list(range(5))
    assert reopens_while_gone >= 3
    assert [f.index for f in second] == list(range(5, 10))  # indices keep counting
    assert not source._thread.is_alive()


def drain_until(source, count: int, took, limit_s: float = 10.0) -> list[Frame]:
    frames = []
    deadline = time.monotonic() + limit_s
    while len(frames) < count and time.monotonic() < deadline:
        frame = source.get(timeout_s=0.1)
        if frame is not None:
            frames.append(took(frame))
    return frames


def camera_paced(path: Path, period_s: float = 0.005) -> PacedCapture:
    """A real cv2.VideoCapture over a video file that hands over a frame every ``period_s``, as a camera does."""

    def wait_a_period() -> bool:
        time.sleep(period_s)
        return True

    return PacedCapture(cv2.VideoCapture(str(path)), wait_a_period)


def test_a_camera_that_hands_over_the_same_image_again_delivers_each_view_once(tmp_path):
    """A driver that repeats its buffer (30 times here): the repeats are counted, not delivered, so no pose
    is sent stamped now from an old image (before, every repeat went on as a new frame)."""
    path = write_video(tmp_path / "cam.avi", 0, numbers=[0, 1, 2, 3, 4] + [4] * 30 + [5, 6, 7, 8, 9])
    source = CaptureSource(lambda: camera_paced(path), name="test", stall_timeout_s=5.0)
    source.start()
    numbers = []
    deadline = time.monotonic() + 10
    while 9 not in numbers and time.monotonic() < deadline:
        frame = source.get(timeout_s=0.1)
        if frame is not None:
            numbers.append(number_of(frame.image))
    source.close()
    assert 9 in numbers and numbers == sorted(set(numbers)), numbers  # every view once at most, in order
    assert source.counters.repeated == 30 and source.lost_reason is None


def test_a_camera_stuck_on_one_image_is_lost_with_that_reason_and_reopened(tmp_path, caplog):
    """The same image for longer than the stall timeout is a frozen driver or a covered lens: the camera is
    lost with that reason (the daemon's health says it, critical) and reopened; the reason holds until a new
    image comes, and each loss is logged once."""
    path = write_video(tmp_path / "cam.avi", 0, numbers=[0, 1, 2] + [2] * 200)  # a second of one image
    source = CaptureSource(lambda: camera_paced(path), name="test", stall_timeout_s=0.3,
                           backoff_initial_s=0.05, backoff_max_s=0.1)
    with caplog.at_level(logging.DEBUG, logger="companion.capture.v4l2"):
        source.start()
        deadline = time.monotonic() + 10
        # on a loaded machine the first frames can be late enough for another reason first ('opened, no frame yet')
        while "the same image" not in (source.lost_reason or "") and time.monotonic() < deadline:
            source.get(timeout_s=0.05)
        reason, reopens = source.lost_reason, source.counters.reopens
        while source.counters.reopens <= reopens and time.monotonic() < deadline:
            source.get(timeout_s=0.05)
        # reopened, the file starts again: a new image (the newest of 0, 1, 2 when taken), and the reason goes
        frame = None
        while frame is None and time.monotonic() < deadline:
            frame = source.get(timeout_s=0.05)
        back = source.lost_reason
        source.close()
    # the time said is the stall timeout or, on a loaded machine, a little more
    said = re.fullmatch(r"camera test: the same image over and over for (\d+\.\d) s \(a frozen driver, or a "
                        r"covered lens\)", reason or "")
    assert said and float(said.group(1)) >= 0.3, reason
    assert frame is not None and frame.index >= 3 and number_of(frame.image) in (0, 1, 2) and back is None
    lost = [r for r in caplog.records if "same image" in r.getMessage()]
    assert lost and lost[0].levelno == logging.WARNING


def test_a_camera_that_opens_but_delivers_nothing_stays_lost_and_is_logged_once(tmp_path, caplog):
    """Reopened again and again, each time without a new frame (a video of one frame: its one image, then
    nothing): the lost reason never clears between reopens, so the daemon's health stays "camera lost"
    instead of flipping to "stalled" and back (a CRITICAL message each time), and the log says it once."""
    path = write_video(tmp_path / "cam.avi", 1)
    source = CaptureSource(lambda: camera_paced(path), name="test", stall_timeout_s=0.1,
                           backoff_initial_s=0.02, backoff_max_s=0.05)
    reasons = []
    with caplog.at_level(logging.DEBUG, logger="companion.capture.v4l2"):
        source.start()
        deadline = time.monotonic() + 10
        while source.counters.reopens < 8 and time.monotonic() < deadline:
            source.get(timeout_s=0.005)
            reasons.append(source.lost_reason)
        source.close()
    since_lost = reasons[next(i for i, r in enumerate(reasons) if r is not None):]
    assert source.counters.reopens >= 8 and None not in since_lost
    assert set(since_lost) == {"camera test: no frame for 0.1 s", "camera test: opened, no frame yet"}
    said = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage().split(";")[0] for r in said] == ["camera test: no frame for 0.1 s"]


def test_missing_v4l2_camera_is_retried_with_backoff_until_closed():
    """The real V4L2 backend on a device that is not there: the thread keeps retrying
    (doubling its wait) instead of failing, and stops promptly on close."""
    source = v4l2_source("/dev/video97", width=640, height=480, fps=30, pixel_format="MJPG", stall_timeout_s=0.2)
    source.backoff_initial_s, source.backoff_max_s = 0.02, 0.08
    source.start()
    deadline = time.monotonic() + 5
    while source.counters.reopens < 4 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert source.counters.reopens >= 4 and not source.connected.is_set()
    assert source.get(timeout_s=0.05) is None and not source.finished
    source.close()
    assert not source._thread.is_alive()
    assert source.error is None


# ------------------------------------------------ issue 11: nothing floods

def test_a_looping_replay_whose_files_vanish_is_paced_reported_once_and_retried(tmp_path, caplog):
    """The files of a looping real-time replay are deleted while it runs: the unreadable
    frames are paced at the recorded rate (not read in a tight loop), the log says so a
    few times (not once per frame), the source reports itself lost with the files missing,
    and frames put back are played again."""
    folder = write_sequence(tmp_path / "seq", 10)  # 10 frames at 50 fps: 0.2 s a loop
    source = replay_source(folder, realtime=True, loop=True)
    source.backoff_initial_s, source.backoff_max_s = 0.05, 0.2
    caplog.set_level("DEBUG", logger="companion.capture")
    source.start()
    assert len(drain_until(source, 10, took=lambda f: f)) == 10
    hidden = tmp_path / "hidden"
    (folder / "frames").rename(hidden)
    deadline = time.monotonic() + 10
    while source.lost_reason is None and time.monotonic() < deadline:
        time.sleep(0.02)
    lost_reason = source.lost_reason
    time.sleep(1.5)
    corrupt_while_gone = source.counters.corrupt
    records_while_gone = [r for r in caplog.records if r.levelno >= 30]
    hidden.rename(folder / "frames")
    back = drain_until(source, 10, took=lambda f: f)
    source.close()
    # the files are gone, which the reason says (it said "N frames in a row unreadable")
    assert lost_reason is not None and lost_reason.endswith(f" missing ({folder / 'frames'})"), lost_reason
    # At 50 fps, 1.5 s and more of vanished files are at most a few hundred frames, not hundreds of thousands.
    assert 0 < corrupt_while_gone < 200, corrupt_while_gone
    assert len(records_while_gone) <= 4, [r.getMessage() for r in records_while_gone]
    assert any("unreadable" in r.getMessage() for r in records_while_gone)
    assert len(back) == 10 and source.lost_reason is None
    assert any("readable again" in r.getMessage() for r in caplog.records)


def test_v4l2_cannot_open_names_a_missing_device(tmp_path):
    from companion.capture.v4l2 import device_problem

    problem = device_problem(str(tmp_path / "video7"))
    assert "does not exist" in problem and "video7" in problem


def test_v4l2_cannot_open_names_the_group_that_may_read_the_device():
    """A device node this user may not open: the message names its group. Checked as an
    unprivileged user (a forked child that drops root), so that root's override does not
    hide the problem."""
    import grp
    import os
    import shutil
    import tempfile

    from companion.capture.v4l2 import device_problem

    folder = Path(tempfile.mkdtemp(dir="/tmp"))
    try:
        os.chmod(folder, 0o755)
        device = folder / "video5"
        device.write_bytes(b"")
        group = grp.getgrgid(os.stat(device).st_gid).gr_name
        os.chmod(device, 0o660 if os.geteuid() == 0 else 0o000)
        read_end, write_end = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: drop root if we have it, diagnose, report through the pipe
            try:
                if os.geteuid() == 0:
                    os.setgid(65534)
                    os.setuid(65534)
                os.write(write_end, device_problem(str(device)).encode())
            finally:
                os._exit(0)
        os.close(write_end)
        with os.fdopen(read_end) as pipe:
            problem = pipe.read()
        os.waitpid(pid, 0)
    finally:
        shutil.rmtree(folder)
    assert "permission" in problem and f"group {group}" in problem, problem


def test_backoff_doubles_to_its_cap_and_starts_over_after_a_success():
    """The camera's and the replay's waits between attempts (one schedule for both): doubling to its cap, so
    that a camera lost for long is retried every 2 s (the sources' default cap), and from the start again
    once it delivered."""
    backoff = Backoff(0.5, 2.0)
    assert [backoff.next_s() for _ in range(5)] == [0.5, 1.0, 2.0, 2.0, 2.0]
    backoff.reset()
    assert backoff.next_s() == 0.5
