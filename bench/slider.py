#!/usr/bin/python3
"""Slider drag through a real server: springblend-server on a free loopback port with a temporary cache
directory, the five-expression ICT face uploaded with the Python client, then one Interactive session that is
sent FPS frames per second for SECONDS seconds along a smooth slider path while another thread reads the
answers. Reports answers per second, latency (a frame's send to its answer), and the time from the last frame
sent to its converged answer; writes OUT/slider.md and OUT/slider.json.

    /usr/bin/python3 bench/slider.py [--build build/bench] [--out bench-results] [--shared DIR]
                                     [--fps 20] [--seconds 6]

Needs the Python client assembled by the build (BUILD/python, target springblend_python) and Debian's
python3-grpcio and python3-numpy. Skips cleanly (exit 0, a note in slider.md) when the face is not there.
"""

import argparse
import json
import math
import os
import pathlib
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
FACE_FILES = ("generic_neutral_mesh.obj", "jawOpen.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "eyeBlink_L.obj",
              "browInnerUp_L.obj")
# The slider path: weight j follows amplitude * (1 - cos(2 pi t / period)) / 2, so every slider starts at 0,
# moves smoothly (no jumps between frames) and the five move at different rates.
AMPLITUDES = (0.6, 0.5, 0.5, 0.8, 0.7)
PERIODS_S = (6.0, 4.0, 5.0, 3.0, 6.0)


def load_obj(path):
    """(#V by 3 float64 positions rounded to float32 as the C++ loader does, #F by 3 int32 triangles)."""
    import numpy as np
    vertices, faces = [], []
    with open(path) as obj:
        for line in obj:
            fields = line.split()
            if not fields:
                continue
            if fields[0] == "v":
                vertices.append([float(v) for v in fields[1:4]])
            elif fields[0] == "f":
                corners = [int(f.split("/")[0]) - 1 for f in fields[1:]]
                faces += [[corners[0], corners[k], corners[k + 1]] for k in range(1, len(corners) - 1)]
    return (np.array(vertices, dtype=np.float32).astype(np.float64), np.array(faces, dtype=np.int32))


def drag(client, character, args, count, previews):
    """One Interactive session: count frames at args.fps along the slider path; the answers' figures."""
    sent = [None] * count       # monotonic send time per index
    answers = []                # (index, received, converged, newton_iterations, solve_ms)
    errors = []
    with client.interactive(character.id, previews=previews) as session:
        def read():
            try:
                for frame in session:
                    s = frame.summary
                    answers.append((frame.index, time.monotonic(), bool(s.converged), int(s.newton_iterations),
                                    float(s.solve_ms)))
            except Exception as error:  # reported below; the drag itself goes on
                errors.append(repr(error))

        reader = threading.Thread(target=read)
        reader.start()
        t0 = time.monotonic()
        for k in range(count):
            due = t0 + k / args.fps
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            sent[k] = time.monotonic()
            session.send(weights_at(k / args.fps))
        last_sent = sent[-1]
        session.close()
        reader.join(600.0)
    if errors:
        raise RuntimeError(f"the session failed: {errors[0]}")
    latencies = [received - sent[index] for index, received, *_ in answers]
    solved = [a for a in answers if a[2]]
    during = [a for a in answers if a[1] <= last_sent]
    last = [a for a in answers if a[0] == count - 1 and a[2]] or [a for a in answers if a[0] == count - 1]
    first_sent = sent[0]
    last_received = max((a[1] for a in answers), default=first_sent)
    return {
        "previews": previews, "answers": len(answers), "answers_converged": len(solved),
        "answers_during_drag": len(during),
        "answers_per_s": len(answers) / max(1e-9, last_received - first_sent),
        "answers_per_s_during_drag": len(during) / max(1e-9, last_sent - first_sent),
        "latency_median_ms": 1000 * statistics.median(latencies) if latencies else None,
        "latency_max_ms": 1000 * max(latencies) if latencies else None,
        "converged_latency_median_ms":
            1000 * statistics.median(a[1] - sent[a[0]] for a in solved) if solved else None,
        "last_frame_to_answer_ms": 1000 * (last[-1][1] - last_sent) if last else None,
        "last_answer_converged": bool(last[-1][2]) if last else None,
        "solve_ms_median": statistics.median(a[4] for a in solved) if solved else None,
        "newton_iterations_median": statistics.median(a[3] for a in solved) if solved else None,
        "frames": [{"index": a[0], "latency_ms": 1000 * (a[1] - sent[a[0]]), "converged": a[2],
                    "newton_iterations": a[3], "solve_ms": a[4]} for a in answers],
    }


def weights_at(t):
    return [a * 0.5 * (1.0 - math.cos(2.0 * math.pi * t / p)) for a, p in zip(AMPLITUDES, PERIODS_S)]


class Server:
    """springblend-server on 127.0.0.1:0 with a temporary cache directory; a context manager."""

    def __init__(self, binary, startup_s=60.0):
        self.directory = tempfile.mkdtemp(prefix="springblend-slider-")
        self.log_path = os.path.join(self.directory, "server.log")
        self._log = open(self.log_path, "w")
        self.process = subprocess.Popen([binary, "--listen", "127.0.0.1:0", "--cache-dir",
                                         os.path.join(self.directory, "cache")],
                                        stdout=subprocess.PIPE, stderr=self._log, text=True)
        found = []

        def read():
            for line in self.process.stdout:
                if "listening on" in line:
                    found.append(line.rsplit(" ", 1)[-1].strip())
                    return

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(startup_s)
        if not found:
            self.stop()
            raise RuntimeError(f"springblend-server did not start within {startup_s} s")
        self.address = found[0]

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def machine_line():
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
    try:
        git = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"], capture_output=True,
                             text=True).stdout.strip() or "n/a"
    except OSError:
        git = "n/a"
    return (f"machine: nproc {os.cpu_count()}, {cpu}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
            f"git {git}")


def write(out, markdown, figures):
    out.mkdir(parents=True, exist_ok=True)
    (out / "slider.md").write_text(markdown)
    (out / "slider.json").write_text(json.dumps(figures, indent=2) + "\n")
    print(markdown, end="")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build", default=str(REPO / "build" / "bench"))
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--shared", default=str(REPO.parent / "shared" / "meshes"))
    parser.add_argument("--fps", type=float, default=20.0)
    parser.add_argument("--seconds", type=float, default=6.0)
    args = parser.parse_args()
    build, out = pathlib.Path(args.build), pathlib.Path(args.out)
    face = pathlib.Path(args.shared) / "face6706"
    header = "# springblend slider drag\n\n" + machine_line() + "\n\n"

    missing = [f for f in FACE_FILES if not (face / f).is_file()]
    if missing:
        write(out, header + f"Skipped: {face / missing[0]} is missing.\n", {"skipped": True, "missing": missing})
        return 0
    server_binary = build / "server" / "springblend-server"
    if not os.access(server_binary, os.X_OK):
        print(f"slider.py: {server_binary} is missing; build the bench configuration first", file=sys.stderr)
        return 2
    sys.path.insert(0, str(build / "python"))
    try:
        import springblend
    except ImportError as error:
        print(f"slider.py: cannot import the Python client from {build / 'python'} ({error}); build the target "
              "springblend_python", file=sys.stderr)
        return 2

    rest, faces = load_obj(face / FACE_FILES[0])
    targets = {pathlib.Path(f).stem: load_obj(face / f)[0] for f in FACE_FILES[1:]}
    count = int(round(args.fps * args.seconds))
    with Server(str(server_binary)) as server, springblend.Client(server.address, timeout=600.0) as client:
        start = time.monotonic()
        character = client.upload(rest, faces, targets, name="face-mix")
        upload_s = time.monotonic() - start

        runs = [drag(client, character, args, count, previews) for previews in (False, True)]

    figures = {"fps": args.fps, "seconds": args.seconds, "frames_sent": count, "upload_s": upload_s,
               "vertices": int(character.summary.vertices),
               "server_precompute_ms": float(character.summary.precompute_ms),
               "without_previews": runs[0], "with_previews": runs[1]}

    def ms(value):
        return "-" if value is None else f"{value:.0f}"

    def row(name, run):
        unconverged = "" if run["last_answer_converged"] in (None, True) else " (not converged)"
        return (f"| {name} | {count} | {run['answers']} | {run['answers_converged']} | "
                f"{run['answers_per_s_during_drag']:.1f} | {ms(run['latency_median_ms'])} | "
                f"{ms(run['latency_max_ms'])} | {ms(run['converged_latency_median_ms'])} | "
                f"{ms(run['last_frame_to_answer_ms'])}{unconverged} | {ms(run['solve_ms_median'])} | "
                f"{run['newton_iterations_median']} |\n")

    markdown = header + (
        f"ICT face with five expressions (jawOpen, mouthSmile_L, mouthSmile_R, eyeBlink_L, browInnerUp_L; "
        f"{figures['vertices']} simulated vertices), uploaded with the Python client to a springblend-server on "
        f"loopback (default workers, temporary cache; upload and build {upload_s:.1f} s, of which rig build "
        f"{figures['server_precompute_ms'] / 1000:.1f} s). One Interactive session; {count} frames sent at "
        f"{args.fps:g} per second for {args.seconds:g} s along a smooth path (each slider "
        f"a * (1 - cos(2 pi t / T)) / 2), answers read on another thread, once without and once with previews. "
        f"The server answers the newest frame it has and drops overtaken ones.\n\n"
        "| session | frames sent | answers | converged | answers/s during the drag | latency median ms "
        "| latency max ms | converged latency median ms | last frame sent to its converged answer ms "
        "| server solve ms median | Newton it median |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
        + "".join(row(name, run) for name, run in (("solves only", runs[0]), ("with previews", runs[1]))) + "\n"
        "Latency: from a frame's send to its answer (a preview or a solve), over the answers; converged latency: "
        "the same over the solved answers only. With previews (InteractiveStart.previews) every frame taken up is "
        "answered at once by the rig's prediction, then solved unless a newer frame overtakes it. Every frame's "
        "figures: slider.json.\n")
    write(out, markdown, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
