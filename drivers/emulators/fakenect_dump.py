"""Writes a libfreenect "fakenect" dump, so the real library plays RGB-D frames back to a driver.

The format is what libfreenect's ``record`` tool writes and ``fakenect`` reads
(OpenKinect/libfreenect fakenect/record.c and fakenect.c):

    DUMP/INDEX.txt                      one file name per line, in playback order
    DUMP/r-<time s>-<timestamp>.ppm     "P6 640 480 255\\n" + 640x480 RGB bytes
    DUMP/d-<time s>-<timestamp>.pgm     "P5 640 480 65535\\n" + 640x480 uint16 in HOST byte order
                                        (fakenect memcpy()s it; not the big-endian of the PGM spec)

fakenect sleeps between lines so the playback keeps the recorded times, and its
``freenect_process_events`` returns -1 after the last line (0.5.3 does not loop). A gap in the
recorded times is therefore a device that goes silent while still "plugged in", and the end of the
dump is a device that stops with an error.

The depth frames written here hold **registered depth in millimetres** (0 = no reading), what a
Kinect delivers in ``FREENECT_DEPTH_REGISTERED`` mode: the driver asks for that mode, and the
preloaded stub (``fakenect_stub.c``, see there why) lets Debian's fakenect accept it.

    python -m drivers.emulators.fakenect_dump --scene greenhouse --frames 20 --out /tmp/dump
        [--fps 15] [--seed 0] [--gap-after N --gap-s S] [--stub-dir DIR]

prints one JSON line: the dump, the number of frames, and (with --stub-dir) the environment to
run a program under fakenect.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 640, 480
STUB_SOURCE = Path(__file__).with_name("fakenect_stub.c")


def depth_to_mm(depth_m: np.ndarray, depth_unit_m: float = 0.001) -> np.ndarray:
    """float32 metres (0 = none) -> uint16 counts of ``depth_unit_m`` (0 = none, clipped to the
    Kinect's 10 000 mm maximum)."""
    d = np.asarray(depth_m, np.float64)
    mm = np.where(np.isfinite(d) & (d > 0), np.rint(d / depth_unit_m), 0)
    return np.clip(mm, 0, 10000).astype(np.uint16)


class DumpWriter:
    """Appends colour+depth frames to a fakenect dump (``INDEX.txt`` + ``r-*.ppm`` + ``d-*.pgm``).

    ``t0_s`` is the recorded start time; each :meth:`add` advances the recorded clock by
    ``1/fps`` (plus any ``gap_s`` given), the device timestamp by the Kinect's 60 MHz-ish tick
    equivalent of the same time (only its order matters to fakenect)."""

    def __init__(self, out: str | Path, fps: float = 15.0, t0_s: float = 1000.0):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        if (self.out / "INDEX.txt").exists():
            raise FileExistsError(f"{self.out}/INDEX.txt exists: write a dump to a new folder")
        self.fps = float(fps)
        self.t = float(t0_s)
        self.frames = 0
        self._written: list[tuple[Path, Path]] = []
        self._index = open(self.out / "INDEX.txt", "w")

    def _file(self, kind: str, t: float, ts: int, ext: str, header: bytes, data: bytes,
              link_to: Path | None = None) -> Path:
        name = f"{kind}-{t:f}-{ts}.{ext}"
        if link_to is None:
            (self.out / name).write_bytes(header + data)
        else:
            os.link(link_to, self.out / name)      # the same bytes: a long dump costs nothing
        self._index.write(name + "\n")
        return self.out / name

    def again(self, k: int) -> None:
        """Frame ``k`` (0-based, already written) once more at the next recorded time, as hard
        links to its files: hours of playback in the space of the frames themselves."""
        r, d = self._written[k]
        ts = int(self.t * 1e6) & 0xFFFFFFFF
        self._file("r", self.t, ts, "ppm", b"", b"", link_to=r)
        self._file("d", self.t + 0.001, (ts + 1000) & 0xFFFFFFFF, "pgm", b"", b"", link_to=d)
        self.frames += 1
        self.t += 1.0 / self.fps

    def add(self, color_bgr: np.ndarray, depth_mm: np.ndarray, gap_s: float = 0.0) -> None:
        c = np.asarray(color_bgr)
        d = np.asarray(depth_mm)
        if c.shape != (HEIGHT, WIDTH, 3) or c.dtype != np.uint8:
            raise ValueError(f"colour must be {HEIGHT}x{WIDTH}x3 uint8, got {c.shape} {c.dtype}")
        if d.shape != (HEIGHT, WIDTH) or d.dtype != np.uint16:
            raise ValueError(f"depth must be {HEIGHT}x{WIDTH} uint16, got {d.shape} {d.dtype}")
        self.t += gap_s
        ts = int(self.t * 1e6) & 0xFFFFFFFF             # a rolling device counter
        rgb = np.ascontiguousarray(c[..., ::-1])
        r = self._file("r", self.t, ts, "ppm", f"P6 {WIDTH} {HEIGHT} 255\n".encode(),
                       rgb.tobytes())
        # depth a millisecond after the colour, as the two streams arrive on a Kinect
        dp = self._file("d", self.t + 0.001, (ts + 1000) & 0xFFFFFFFF, "pgm",
                        f"P5 {WIDTH} {HEIGHT} 65535\n".encode(), d.astype(np.uint16).tobytes())
        self._written.append((r, dp))
        self.frames += 1
        self.t += 1.0 / self.fps

    def close(self) -> None:
        if not self._index.closed:
            self._index.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_frame(path: str | Path) -> np.ndarray:
    """One dump file back as an array (uint16 HxW for ``d-*.pgm``, uint8 HxWx3 RGB for
    ``r-*.ppm``), as fakenect hands it to the library."""
    raw = Path(path).read_bytes()
    head, _, data = raw.partition(b"\n")
    magic, w, h, maxval = head.split()
    w, h = int(w), int(h)
    if magic == b"P5" and int(maxval) == 65535:
        return np.frombuffer(data, np.uint16, w * h).reshape(h, w)
    if magic == b"P6":
        return np.frombuffer(data, np.uint8, w * h * 3).reshape(h, w, 3)
    raise ValueError(f"{path}: not a fakenect frame ({head[:20]!r})")


def sim_dump(out: str | Path, scene: str = "greenhouse", frames: int = 20, seed: int = 0,
             fps: float = 15.0, speed_mps: float | None = None, gap_after: int | None = None,
             gap_s: float = 0.0, repeat: int = 1, link: bool = False) -> dict:
    """A dump of ``frames`` consecutive RGB-D frames of the simulated field (the vehicle driving
    on at ``fps``). ``gap_after=N, gap_s=S``: the recorded clock jumps S seconds after frame N
    (the device goes silent that long). ``repeat``: the rendered frames written that many times
    over (long dumps for benchmarks without rendering more); with ``link`` the repeats are hard
    links to the first pass's files (an hour's dump in the space of ``frames``). Returns
    {"dump", "frames", "calibration"}."""
    from drivers.sim.field import SimField
    from hal.types import GateState
    f = SimField(scene=scene, seed=seed, sensors=("rgbd",), start_speed_mps=speed_mps)
    cal = f.depth_calibration
    if (cal.camera.width, cal.camera.height) != (WIDTH, HEIGHT):
        raise ValueError("the simulated depth camera is not 640x480")
    rendered = []
    for i in range(frames):
        if i:
            f.step(1.0 / fps, GateState.CLEAR)
        fr = f.render_rgbd(0, i + 1)
        rendered.append((fr.color, depth_to_mm(fr.depth_m, cal.depth_unit_m)))
    with DumpWriter(out, fps=fps) as w:
        for k in range(max(1, repeat) * frames):
            if link and k >= frames and not (gap_after is not None and k == gap_after):
                w.again(k % frames)
                continue
            w.add(*rendered[k % frames],
                  gap_s=gap_s if gap_after is not None and k == gap_after else 0.0)
    c = cal.camera
    return {"dump": str(out), "frames": max(1, repeat) * frames,
            "calibration": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                            "depth_unit_m": cal.depth_unit_m, "min_range_m": cal.min_range_m,
                            "max_range_m": cal.max_range_m, "mount_x_m": cal.mount.x_m,
                            "mount_y_m": cal.mount.y_m, "mount_z_m": cal.mount.z_m,
                            "mount_pitch_deg": cal.mount.pitch_deg}}


def with_gap(src: str | Path, dst: str | Path, after_frame: int, gap_s: float,
             keep: int | None = None) -> Path:
    """A copy of dump ``src`` (files hard-linked where possible) in which the recorded clock
    jumps ``gap_s`` after colour+depth frame ``after_frame``: played back, the device goes
    silent that long. ``keep``: only the first so many frames. Any recorded dump works (fakenect
    only reads the times in the names)."""
    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=False)
    out, frame = [], -1
    for name in (src / "INDEX.txt").read_text().split():
        kind, t, rest = name.split("-", 2)
        if kind == "r":
            frame += 1
        if keep is not None and frame >= keep:
            break
        shift = gap_s if frame > after_frame else 0.0
        new = f"{kind}-{float(t) + shift:f}-{rest}"
        try:
            os.link(src / name, dst / new)
        except OSError:
            shutil.copyfile(src / name, dst / new)
        out.append(new)
    (dst / "INDEX.txt").write_text("\n".join(out) + "\n")
    return dst


# ---------------------------------------------------------------------------------------------
# running a program under fakenect
def fakenect_libdir() -> Path | None:
    """The folder holding fakenect's libfreenect.so (Debian: /usr/lib/<triplet>/fakenect)."""
    script = shutil.which("fakenect")
    if script:                                      # the wrapper script names it
        try:
            for line in Path(script).read_text().splitlines():
                if "LD_LIBRARY_PATH=" in line and "fakenect" in line:
                    p = line.split('LD_LIBRARY_PATH="', 1)[1].split(":", 1)[0]
                    if Path(p, "libfreenect.so").exists() or glob.glob(f"{p}/libfreenect.so*"):
                        return Path(p)
        except (OSError, IndexError):
            pass
    for pat in ("/usr/lib/*/fakenect", "/usr/lib/fakenect", "/usr/local/lib/fakenect",
                "/usr/local/lib/*/fakenect"):
        for p in glob.glob(pat):
            if glob.glob(f"{p}/libfreenect.so*"):
                return Path(p)
    return None


def build_stub(out_dir: str | Path) -> Path:
    """Compile fakenect_stub.c into ``out_dir/libfakenect_stub.so`` (needs gcc and
    libfreenect-dev). RuntimeError with the compiler's message if it fails."""
    out = Path(out_dir) / "libfakenect_stub.so"
    if out.exists() and out.stat().st_mtime >= STUB_SOURCE.stat().st_mtime:
        return out
    gcc = shutil.which("gcc") or shutil.which("cc")
    if gcc is None:
        raise RuntimeError("no C compiler (gcc) to build the fakenect stub")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(f".{os.getpid()}.tmp")
    r = subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-I/usr/include/libfreenect", "-o",
                        str(tmp), str(STUB_SOURCE)], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"building the fakenect stub failed: {r.stderr.strip()[-800:]}")
    os.replace(tmp, out)
    return out


def fakenect_env(dump: str | Path, stub: str | Path, base: dict | None = None) -> dict:
    """Environment that makes a process load fakenect (playing ``dump``) instead of the USB
    libfreenect: what the ``fakenect`` wrapper script sets, plus the preloaded stub."""
    libdir = fakenect_libdir()
    if libdir is None:
        raise RuntimeError("fakenect's libfreenect.so not found (install libfreenect-bin)")
    env = dict(os.environ if base is None else base)
    env["FAKENECT_PATH"] = str(Path(dump).resolve())
    env["LD_LIBRARY_PATH"] = f"{libdir}:{env.get('LD_LIBRARY_PATH', '')}".rstrip(":")
    env["LD_PRELOAD"] = f"{Path(stub).resolve()} {env.get('LD_PRELOAD', '')}".strip()
    return env


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.emulators.fakenect_dump",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="greenhouse")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--gap-after", type=int, help="recorded clock jumps after this frame")
    ap.add_argument("--gap-s", type=float, default=0.0)
    ap.add_argument("--repeat", type=int, default=1, help="write the frames this many times")
    ap.add_argument("--out", required=True)
    ap.add_argument("--stub-dir", help="also build the preload stub here; print the environment")
    a = ap.parse_args(argv)
    info = sim_dump(a.out, a.scene, a.frames, a.seed, a.fps, gap_after=a.gap_after,
                    gap_s=a.gap_s, repeat=a.repeat)
    if a.stub_dir:
        stub = build_stub(a.stub_dir)
        env = fakenect_env(a.out, stub, base={})
        info["stub"] = str(stub)
        info["env"] = env
    print(json.dumps(info), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
