"""Writing videos: frame sizes, the frame times of a playback, and an H.264
writer over the bundled ffmpeg (``imageio-ffmpeg``)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["parse_size", "video_times", "VideoWriter"]


def parse_size(text: str, even: bool = True) -> tuple[int, int]:
    """``"1280x720"`` -> ``(1280, 720)``.

    Parameters
    ----------
    text : str
        ``WIDTHxHEIGHT`` [px].
    even : bool
        Require both even (H.264 frames).

    Raises
    ------
    BonesimError
        For anything else.
    """
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise BonesimError(f"size {text!r} is not WIDTHxHEIGHT (e.g. 1280x720)",
                           field="--size") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise BonesimError(f"size {w}x{h} must be 16..8192 pixels each way",
                           field="--size")
    if even and (w % 2 or h % 2):
        raise BonesimError(f"video size {w}x{h}: width and height must be even for "
                           "H.264", field="--size")
    return w, h


def video_times(duration: float, fps: float, speed: float = 1.0, start: float | None = None,
                end: float | None = None) -> np.ndarray:
    """Playback times [s] of the frames of a video.

    Frame ``k`` shows ``start + k * speed / fps``; the video lasts
    ``(end - start) / speed`` seconds, i.e. ``round((end - start) * fps /
    speed)`` frames (at least one).

    Parameters
    ----------
    duration : float
        Recording length [s].
    fps : float
        Video frame rate [Hz].
    speed : float
        Playback speed factor.
    start, end : float, optional
        Part of the recording [s] (default all of it).
    """
    if not fps > 0:
        raise BonesimError(f"frame rate must be positive, got {fps}", field="--fps")
    if not speed > 0:
        raise BonesimError(f"speed must be positive, got {speed}", field="--speed")
    a = 0.0 if start is None else float(start)
    b = float(duration) if end is None else float(end)
    if not (0.0 <= a <= duration) or not math.isfinite(a):
        raise BonesimError(f"start {a:g} s lies outside the recording (0 .. "
                           f"{duration:.3f} s)", field="--start")
    if not (0.0 <= b <= duration + 1e-9) or not math.isfinite(b):
        raise BonesimError(f"end {b:g} s lies outside the recording (0 .. "
                           f"{duration:.3f} s)", field="--end")
    if b <= a:
        raise BonesimError(f"end {b:g} s is not after start {a:g} s", field="--end")
    n = max(1, int(round((b - a) * fps / speed)))
    return np.minimum(a + np.arange(n) * (speed / fps), b)


class VideoWriter:
    """H.264 mp4 encoded by the ffmpeg that imageio-ffmpeg bundles.

    Frames are piped raw (RGB) into one ffmpeg process (libx264, yuv420p,
    ``-crf`` quality, ``+faststart``); its messages are kept and quoted in
    the error if it fails. A video that fails or is aborted (an exception
    inside the ``with`` block) is deleted.

    Parameters
    ----------
    path : path
        Output file (``.mp4``); its folder must exist and be writable.
    size : (int, int)
        Frame width and height [px], both even.
    fps : float
        Frame rate [Hz].
    crf : int
        x264 constant rate factor (0 lossless .. 51 worst; 18-23 look good).
    preset : str
        x264 speed preset.

    Raises
    ------
    BonesimError
        Unwritable output, odd size, or ffmpeg failing.
    """

    def __init__(self, path, size, fps: float = 30.0, crf: int = 20,
                 preset: str = "veryfast"):
        import subprocess
        import tempfile

        import imageio_ffmpeg

        self.path = Path(path)
        self.size = (int(size[0]), int(size[1]))
        w, h = self.size
        if w % 2 or h % 2 or w < 2 or h < 2:
            raise BonesimError(f"frame size {w}x{h} must be even (and positive) for H.264",
                               self.path)
        if not fps > 0:
            raise BonesimError(f"frame rate must be positive, got {fps}", self.path)
        if self.path.is_dir():
            raise BonesimError("is a folder, not a video file name", self.path)
        if not self.path.parent.is_dir():
            raise BonesimError("the output folder does not exist", self.path)
        try:
            with open(self.path, "wb"):
                pass
        except OSError as exc:
            raise BonesimError(f"cannot write the video: {exc.strerror or exc}",
                               self.path) from None
        try:
            exe = imageio_ffmpeg.get_ffmpeg_exe()
        except RuntimeError as exc:
            raise BonesimError(f"no ffmpeg found for the video export: {exc}",
                               self.path) from None
        self.cmd = [exe, "-y", "-hide_banner", "-loglevel", "error",
                    "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
                    "-r", f"{float(fps):g}", "-i", "-", "-an",
                    "-c:v", "libx264", "-preset", str(preset), "-crf", str(int(crf)),
                    "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(self.path)]
        self.frames = 0
        self._log = tempfile.TemporaryFile()
        try:
            self._proc = subprocess.Popen(self.cmd, stdin=subprocess.PIPE,
                                          stdout=subprocess.DEVNULL, stderr=self._log)
        except OSError as exc:
            self._log.close()
            raise BonesimError(f"could not start ffmpeg ({exe}): {exc}", self.path) from None

    def _failed(self, what: str) -> BonesimError:
        proc, self._proc = self._proc, None
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            code = proc.wait(timeout=30)
        except Exception:  # noqa: BLE001 - a hung ffmpeg is killed, the error stands
            proc.kill()
            code = proc.wait()
        self._log.seek(0)
        said = self._log.read().decode("utf-8", "replace").strip().splitlines()
        self._log.close()
        self._discard()
        if not said:
            tail = "no message"
        elif len(said) <= 3:
            tail = "; ".join(said)
        else:                         # the cause comes first, the outcome last
            tail = "; ".join(said[:2]) + " ... " + said[-1]
        return BonesimError(f"ffmpeg failed {what} (exit status {code}): {tail}", self.path)

    def write(self, rgb: np.ndarray) -> None:
        """Append one frame: (height, width, 3) uint8 RGB, first row at the top."""
        if self._proc is None:
            raise ValueError("the video is closed")
        a = np.ascontiguousarray(rgb, dtype=np.uint8)
        w, h = self.size
        if a.shape != (h, w, 3):
            raise ValueError(f"frame of shape {a.shape}, expected {(h, w, 3)}")
        try:
            self._proc.stdin.write(a.data)
        except (BrokenPipeError, OSError):
            raise self._failed(f"at frame {self.frames}") from None
        self.frames += 1

    def close(self) -> None:
        """Finish the file (waits for ffmpeg); raises if ffmpeg failed."""
        proc = self._proc
        if proc is None:
            return
        try:
            proc.stdin.close()
        except OSError:
            pass
        code = proc.wait()
        if code != 0:
            raise self._failed("finishing the file")
        self._proc = None
        self._log.close()

    def abort(self) -> None:
        """Stop ffmpeg and delete the unfinished file (after an error elsewhere)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        proc.kill()
        proc.wait()
        self._log.close()
        self._discard()

    def _discard(self) -> None:
        """Remove the unfinished output: a broken mp4 is worse than none."""
        try:
            self.path.unlink()
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *_):
        if exc_type is None:
            self.close()
        else:
            self.abort()
