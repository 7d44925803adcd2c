from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
sys.path.insert(0, str(TESTS))
sys.path.insert(0, str(TESTS / "external_plugin"))

from synthetic_pairs import Pit, calib_for, render  # noqa: E402

from drivers.sequence_folder import write_calibration, write_frame  # noqa: E402


def pytest_sessionstart(session):
    """Fill numba's cache once before any test runs (in the controller of a run on several workers): in a fresh
    checkout every worker and every `inspect` process a test started compiled the same kernels again until one
    had written them, some 70 s of CPU each. Two processes compile different kernels at once
    (``plugins/torch_sgm/kernel_warm_up.py``), the first at one thread and at two. Where the cache is warm this takes
    a few seconds."""
    if hasattr(session.config, "workerinput"):  # a worker: the controller warmed it
        return
    from plugins.torch_sgm import kernel_warm_up

    # a warm-up that fails leaves the kernels to the tests, which then say why
    for process in [kernel_warm_up.start("first", {}, (1, 2)), kernel_warm_up.start("later", {})]:
        kernel_warm_up.finish(process)


def write_plane_sequence(folder: Path, pit_depths_mm: list[float], width: int = 320, height: int = 192,
                         focal_px: float = 350.06, distance_mm: float = 400.0, tilt_deg: float = 5.0) -> dict:
    """One frame per entry: a tilted plate with a pit of that depth (0 = no pit) centred in the image.

    Returns the pit's box in the left image.
    """
    calib = calib_for(width, height, focal_px)
    write_calibration(folder, dict(focal_px=calib.focal_px, baseline_mm=calib.baseline_mm, cx=calib.cx,
                                   cy=calib.cy, width=width, height=height, doffs=0.0))
    u, v = width / 2, height / 2
    for i, depth in enumerate(pit_depths_mm):
        pits = [Pit(u, v, 25.0, depth)] if depth else []
        left, right, disparity = render(calib, distance_mm, tilt_deg, pits, seed=i)
        write_frame(folder, f"{i:06d}", left, right, disparity)
    return {"box": [u - 25, v - 25, u + 25, v + 25], "calib": calib}


@pytest.fixture
def plane_sequence(tmp_path):
    def make(pit_depths_mm, **kw):
        folder = tmp_path / "seq"
        info = write_plane_sequence(folder, pit_depths_mm, **kw)
        info["folder"] = folder
        return info
    return make


def write_recipe(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


NEU_FIXTURES = TESTS / "fixtures" / "neu_val"


def neu_fixture_dataset(root: Path) -> Path:
    """The committed NEU-DET val fixtures as a YOLO dataset under ``root`` (all five in both splits),
    converted by ``convert_voc`` from a VOC layout; returns the dataset folder."""
    from plugins.yolov8.voc_to_yolo import convert_voc

    src = root / "voc"
    (src / "images").mkdir(parents=True)
    (src / "annotations").mkdir()
    for image in NEU_FIXTURES.glob("*.jpg"):
        shutil.copy(image, src / "images")
        shutil.copy(image.with_suffix(".xml"), src / "annotations")
    stems = "\n".join(sorted(p.stem for p in NEU_FIXTURES.glob("*.jpg"))) + "\n"
    for split in ("train", "val"):
        (src / f"{split}.txt").write_text(stems)
    convert_voc(src, root / "yolo", {"train": src / "train.txt", "val": src / "val.txt"})
    return root / "yolo"


def cli(*args: str, env_extra: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the installed ``inspect`` console script for real, as a user would."""
    env = dict(os.environ, **(env_extra or {}))
    exe = Path(sys.executable).parent / "inspect"
    return subprocess.run([str(exe), *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def cli_here(*args: str) -> subprocess.CompletedProcess:
    """``cli`` in this process: the console script's own entry point (``core.cli.main``) with its output
    captured. For the commands that are refused before they do any work, whose start as a process of their
    own (torch imported again, 2-3 s) is most of what such a test costs. An exception that escapes ``main``
    is written to the captured stderr as a traceback, as the console script would, and exits 1."""
    import traceback

    from click.testing import CliRunner

    from core.cli import main

    # the allocator's switch is process-wide: left as it is here (tests/test_memory.py checks it)
    with CliRunner().isolation(env={"STEREO_INSPECT_KEEP_MEMORY": "0"}) as (out, err, _):
        try:
            main(list(args))
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except Exception:
            traceback.print_exc()
            code = 1
        stdout, stderr = out.getvalue().decode(), err.getvalue().decode()
    return subprocess.CompletedProcess(["inspect", *args], code, stdout, stderr)


@pytest.fixture(scope="session")
def external_plugin_site(tmp_path_factory) -> Path:
    """The example third-party plugin package, installed by pip into a folder of its own."""
    site = tmp_path_factory.mktemp("site")
    # Build from a copy: an in-tree build leaves an egg-info that would itself register the plugin.
    source = tmp_path_factory.mktemp("src") / "external_plugin"
    shutil.copytree(TESTS / "external_plugin", source, ignore=shutil.ignore_patterns("*.egg-info", "build", "__pycache__"))
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(site),
         str(source)],
        check=True, capture_output=True, timeout=300,
    )
    return site


@pytest.fixture
def torch_one_thread():
    """Torch on one thread: on two shared cores a second thread mostly waits for other jobs."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def start_pty_pair(folder: Path) -> tuple[subprocess.Popen, Path, Path]:
    """Two ends of a real serial line, a socat pseudo-terminal pair, as links in ``folder``.
    Skips the test when socat is missing; the caller terminates the returned process."""
    if shutil.which("socat") is None:
        pytest.skip("socat not installed (apt-get install socat)")
    a, b = folder / "ttyA", folder / "ttyB"
    proc = subprocess.Popen(["socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 5
    while not (a.exists() and b.exists()) and time.monotonic() < deadline:
        time.sleep(0.02)
    return proc, a, b


@pytest.fixture
def pty_pair(tmp_path):
    proc, a, b = start_pty_pair(tmp_path)
    yield str(a), str(b)
    proc.terminate()
    proc.wait(5)


def png_declaring(width: int, height: int) -> bytes:
    """A whole, valid grey PNG of ``width`` x ``height`` black pixels: a few hundred KB that decode to that size."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    packer = zlib.compressobj(9)
    row = b"\x00" * (width + 1)
    pixels = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", pixels) + chunk(b"IEND", b""))
