"""Distracting Control as the paper ran it: DAVIS-2017 backgrounds from the cache (`--backgrounds
davis`), their download (`python envs.py --fetch-davis`), the original suite's split, video counts
and whole-frame resizing, and the start-up line of the procedural default.

No test touches the internet: the download is tested against an archive of the official layout,
built here and served from 127.0.0.1.
"""
import errno
import hashlib
import http.server
import io
import os
import re
import socket
import subprocess
import sys
import threading
import types
import zipfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import envs  # noqa: E402
from envs import DAVIS17_TRAIN, DAVIS17_VAL, EnvError, FetchError  # noqa: E402

RED, BLUE = (230, 10, 10), (10, 10, 230)   # train videos red, validation videos blue
NAME = "DAVIS-2017-trainval-480p.zip"


def jpeg(colour, size=(28, 16)) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.full((size[1], size[0], 3), colour, np.uint8)).save(out, "JPEG")
    return out.getvalue()


def davis_files(frames=2) -> dict:
    """{path in the archive: bytes} of the official trainval 480p layout, with tiny frames."""
    files = {"DAVIS/README.md": b"DAVIS 2017\n", "DAVIS/Annotations/480p/bear/00000.png": b"not needed",
             "DAVIS/ImageSets/2017/train.txt": "\n".join(DAVIS17_TRAIN).encode() + b"\n",
             "DAVIS/ImageSets/2017/val.txt": "\n".join(DAVIS17_VAL).encode() + b"\n"}
    for names, colour in ((DAVIS17_TRAIN, RED), (DAVIS17_VAL, BLUE)):
        for v in names:
            for i in range(frames):
                files[f"DAVIS/JPEGImages/480p/{v}/{i:05d}.jpg"] = jpeg(colour)
    return files


def zipped(files: dict) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for path, data in files.items():
            z.writestr(path, data)
    return out.getvalue()


@pytest.fixture(scope="module")
def archive() -> bytes:
    return zipped(davis_files())


def write_cache(root: Path, skip=()) -> Path:
    """An unpacked cache as --fetch-davis leaves it: <root>/DAVIS/JPEGImages/480p/<video>/*.jpg."""
    for path, data in davis_files().items():
        if path.startswith("DAVIS/JPEGImages/") and path.split("/")[3] not in skip:
            (root / path).parent.mkdir(parents=True, exist_ok=True)
            (root / path).write_bytes(data)
    return root / "DAVIS" / "JPEGImages" / "480p"


class Server:
    """`data` at /DAVIS-2017-trainval-480p.zip on 127.0.0.1, with HTTP Range; `cut`: the first
    response stops after that many bytes and drops the connection (an interrupted download)."""

    def __init__(self, data: bytes, cut: int | None = None):
        self.data, self.cut, self.ranges = data, cut, []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                if self.path != f"/{NAME}":
                    self.send_error(404)
                    return
                asked = self.headers.get("Range")
                server.ranges.append(asked)
                start = int(re.fullmatch(r"bytes=(\d+)-", asked)[1]) if asked else 0
                body = server.data[start:]
                self.send_response(206 if asked else 200)
                if asked:
                    self.send_header("Content-Range", f"bytes {start}-{len(server.data) - 1}/{len(server.data)}")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if server.cut is not None and len(server.ranges) == 1:
                    body = body[:server.cut]
                    self.close_connection = True
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/{NAME}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def serve():
    servers = []

    def start(data, cut=None):
        servers.append(Server(data, cut))
        return servers[-1]
    yield start
    for s in servers:
        s.close()


def fetch(cache, server_or_url, data, **kwargs):
    url = getattr(server_or_url, "url", server_or_url)
    kwargs = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest(), "progress": False, **kwargs}
    return envs.fetch_davis(str(cache), url=url, **kwargs)


def test_fetch_resumes_an_interrupted_download_then_unpacks_and_checks(tmp_path, serve, archive):
    cut = len(archive) // 2
    server = serve(archive, cut=cut)
    cache = tmp_path / "cache"
    with pytest.raises(FetchError, match=f"broke off at {cut} of {len(archive)} bytes; run again to resume") as err:
        fetch(cache, server, archive)
    assert "\n" not in str(err.value)
    assert (cache / f"{NAME}.part").stat().st_size == cut and not (cache / "DAVIS").exists()

    frames = fetch(cache, server, archive)
    assert server.ranges == [None, f"bytes={cut}-"]   # the second call asked only for the rest
    assert frames == cache / "DAVIS" / "JPEGImages" / "480p"
    assert sorted(p.name for p in frames.iterdir()) == sorted(DAVIS17_TRAIN + DAVIS17_VAL)
    assert all(len(list((frames / v).glob("*.jpg"))) == 2 for v in DAVIS17_TRAIN + DAVIS17_VAL)
    assert sorted(p.name for p in cache.iterdir()) == ["DAVIS"]   # no archive, no scratch folder left
    assert sorted(p.name for p in (cache / "DAVIS").iterdir()) == ["ImageSets", "JPEGImages"]   # no Annotations

    assert fetch(cache, server, archive) == frames and len(server.ranges) == 2   # complete: nothing to do
    assert envs.Backgrounds(str(cache), "train", "medium").source == "DAVIS 2017 train (8 videos)"


def test_fetch_refuses_a_corrupt_archive_and_keeps_nothing(tmp_path, serve, archive):
    corrupt = bytearray(archive)
    corrupt[len(corrupt) // 3] ^= 0xFF
    server = serve(bytes(corrupt))
    with pytest.raises(FetchError, match=r"SHA-256 [0-9a-f]{16}\.\.\. is not the official archive's") as err:
        fetch(tmp_path, server, archive)   # the good archive's size and checksum are expected
    assert "\n" not in str(err.value) and list(tmp_path.iterdir()) == []


def test_fetch_refuses_an_archive_of_another_layout(tmp_path, serve):
    files = {k: v for k, v in davis_files().items() if "/bear/" not in k}
    other = zipped(files)
    with pytest.raises(FetchError, match=r"not DAVIS-2017 trainval: no frames for 1 videos \(bear\)"):
        fetch(tmp_path, serve(other), other)
    assert list(tmp_path.iterdir()) == []


def closed_port_url():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}/{NAME}"


def test_fetch_errors_are_one_line(tmp_path, serve, archive, monkeypatch):
    server = serve(archive)
    cases = [(server.url.replace(NAME, "missing.zip"), {}, "HTTP 404"),
             (closed_port_url(), {}, "cannot reach http://127.0.0.1"),
             (server.url, {"size": len(archive) + 1}, f"is {len(archive)} bytes, the DAVIS-2017 trainval 480p "
                                                      f"archive is {len(archive) + 1}: not that archive")]
    for url, kwargs, message in cases:
        with pytest.raises(FetchError, match=re.escape(message)) as err:
            fetch(tmp_path / "cache", url, archive, **kwargs)
        assert "\n" not in str(err.value)
    monkeypatch.setattr(envs.shutil, "disk_usage", lambda path: types.SimpleNamespace(free=10))
    with pytest.raises(FetchError, match="has 0 MB free"):
        fetch(tmp_path / "cache", server, archive)
    monkeypatch.undo()

    def disk_full(archive_path, cache):
        raise OSError(errno.ENOSPC, "No space left on device", str(cache / "DAVIS"))
    monkeypatch.setattr(envs, "_unpack_davis", disk_full)
    with pytest.raises(FetchError, match=r"cannot write .*DAVIS: No space left on device \(disk full\)$"):
        fetch(tmp_path / "cache", server, archive)


def run_envs(*args, env=None):
    return subprocess.run([sys.executable, str(ROOT / "envs.py"), *args], capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


def test_fetch_command_exits_non_zero_with_one_line(tmp_path, serve, archive):
    """The command line checks the official size and checksum whatever the URL: a test archive is refused."""
    server = serve(archive)
    for url, message in ((server.url, "not that archive"), (closed_port_url(), "cannot reach"),
                         (server.url.replace(NAME, "x.zip"), "HTTP 404")):
        r = run_envs("--fetch-davis", "--cache", str(tmp_path / "c"), "--davis-url", url)
        errors = [line for line in r.stderr.splitlines() if line.startswith("envs.py: error: ")]
        assert r.returncode == 1 and len(errors) == 1 and message in errors[0], r.stderr
        assert "Traceback" not in r.stderr and not (tmp_path / "c" / "DAVIS").exists()


def test_davis_cache_gives_the_original_suites_videos_per_split_and_difficulty(tmp_path, monkeypatch):
    """background.py: DAVIS17_TRAINING_VIDEOS for training, DAVIS17_VALIDATION_VIDEOS for evaluation,
    the first num_videos of the list (suite_utils.py: easy 4, medium 8, hard all)."""
    monkeypatch.setenv("SEAR_DATA", str(tmp_path))
    frames = write_cache(tmp_path / "davis")
    for split, names in (("train", DAVIS17_TRAIN), ("eval", DAVIS17_VAL)):
        for difficulty, count in (("easy", 4), ("medium", 8), ("hard", len(names))):
            bgs = envs.Backgrounds("davis", split, difficulty)
            assert [g[0].parent.name for g in bgs.groups] == names[:count]
            assert all(len(g) == 2 and g[0].parent.parent == frames for g in bgs.groups)
    for name in ("bear", "blackswan"):   # the first video of each list
        (frames / name / "00000.jpg").unlink(), (frames / name / "00001.jpg").unlink()
    with pytest.raises(EnvError, match=r"lacks 1 of the train videos \(bear\); fetch it again: "
                                       r"python envs.py --fetch-davis") as err:
        envs.Backgrounds("davis", "train", "easy")
    assert "\n" not in str(err.value)


def test_backgrounds_davis_without_the_cache_says_how_to_get_it_and_creates_nothing(tmp_path, monkeypatch):
    empty = tmp_path / "data"
    monkeypatch.setenv("SEAR_DATA", str(empty))
    with pytest.raises(EnvError, match="no DAVIS-2017 in .*; get it .* with: python envs.py --fetch-davis") as err:
        envs.make_env("walker-walk-distracting", backgrounds="davis")
    assert "\n" not in str(err.value)
    r = subprocess.run([sys.executable, str(ROOT / "sear.py"), "--env", "walker-walk-distracting",
                        "--backgrounds", "davis", "--run-root", str(tmp_path / "runs")], capture_output=True,
                       text=True, timeout=300, cwd=tmp_path, env={**os.environ, "SEAR_DATA": str(empty)})
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.splitlines() == [f"sear.py: error: --backgrounds davis: no DAVIS-2017 in {empty / 'davis'}; "
                                     f"get it (833 MB) with: python envs.py --fetch-davis"]
    assert sorted(p.name for p in tmp_path.iterdir()) == []   # no run dir, no cache folder


def sky(obs):
    return obs["pixels"][-3:, :12].astype(float).mean(axis=(1, 2))


def test_davis_train_env_shows_train_videos_and_eval_env_validation_videos(tmp_path, monkeypatch):
    monkeypatch.setenv("SEAR_DATA", str(tmp_path))
    write_cache(tmp_path / "davis")
    for split, channel in (("train", 0), ("eval", 2)):
        env = envs.make_env("walker-walk-distracting", backgrounds="davis", split=split, frame_stack=1,
                            render_quality="fast", render_mask=False)
        assert all(np.argmax(sky(env.reset(seed=s)[0])) == channel for s in range(2))
        env.close()


def bilinear(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """The original suite's resize: bilinear with half-pixel centres, no anti-aliasing (tf.image.resize
    in google-research's background.py; cv2.resize INTER_LINEAR in the packaged fork the authors
    installed), the whole frame to (h, w)."""
    def axis(n_in, n_out):
        src = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
        lo = np.floor(src).astype(int)
        return lo, np.minimum(lo + 1, n_in - 1), src - lo
    y0, y1, ty = axis(img.shape[0], h)
    x0, x1, tx = axis(img.shape[1], w)
    f = img.astype(np.float64)
    rows = f[y0] * (1 - ty)[:, None, None] + f[y1] * ty[:, None, None]
    return rows[:, x0] * (1 - tx)[None, :, None] + rows[:, x1] * tx[None, :, None]


def test_a_frame_is_resized_whole_as_the_original_suite_not_cropped(tmp_path):
    frame = np.zeros((480, 854, 3), np.uint8)
    frame[:, :140], frame[:, 140:714], frame[:, 714:] = RED, (10, 230, 10), BLUE   # outer sixths
    Image.fromarray(frame).save(tmp_path / "wide.png")
    img = envs.Backgrounds(str(tmp_path), "train", "hard").sample(np.random.default_rng(0), 800)
    assert img.shape == (800, 800, 3)
    assert np.argmax(img[:, 0].mean(0)) == 0 and np.argmax(img[:, -1].mean(0)) == 2   # both edges kept
    # Against the original's bilinear on a smooth frame (PIL widens its kernel by 854/800 on the width).
    yy, xx = np.mgrid[0:480, 0:854]
    smooth = np.stack([128 + 100 * np.sin(xx / 37 + c) * np.cos(yy / 23 - c) for c in range(3)], -1).astype(np.uint8)
    Image.fromarray(smooth).save(tmp_path / "wide.png")
    got = envs.Backgrounds(str(tmp_path), "train", "hard").sample(np.random.default_rng(0), 800).astype(float)
    diff = np.abs(got - bilinear(smooth, 800, 800))
    assert diff.mean() < 0.5 and diff.max() <= 3, (diff.mean(), diff.max())


def test_every_run_on_procedural_backgrounds_says_they_are_not_the_papers():
    from harness import cli
    run = types.SimpleNamespace(threads=1)

    def warnings(env, backgrounds):
        cfg = types.SimpleNamespace(env=env, backgrounds=backgrounds, replay_size=10, batch_size=1, seed_frames=0,
                                    action_repeat=2)
        return [w for w in cli.start_warnings(cfg, run) + cli.start_warnings(cfg, run, training=False)
                if "procedural" in w]
    line = ("walker-walk-distracting runs on the built-in procedural backgrounds, not the paper's DAVIS-2017 "
            "videos; for the paper's setting: python envs.py --fetch-davis, then --backgrounds davis")
    assert warnings("walker-walk-distracting", "") == [line, line]   # training and --evaluate
    assert warnings("walker-walk-distracting", "davis") == warnings("walker-walk", "") == []
