"""The module on CPUs without AVX2 and without AVX, under QEMU's x86-64 emulator.

The kernels are compiled once per ISA level and the core around them for SSE2, so a
portable wheel must run on any x86-64 CPU. Forcing a path with VASTRAY_ISA
(test_kernels.py) cannot show that: the core still runs on this machine's CPU, and an AVX
instruction that leaked into it (an inline function of a header that a kernel compiled
with AVX and the linker kept) would go unnoticed. So the same script runs here and under
`qemu-x86_64 -cpu Nehalem` (SSE4.2, no AVX) and `-cpu SandyBridge` (AVX, no AVX2, no
FMA), where such an instruction is an illegal instruction, and must:

* pick the best path that CPU has (`sse2`, `avx`) and list no better one;
* render every shading mode in core and out of core, answer the batch and pick queries,
  and build a model, with the very answers and file bytes of this machine's run.

The inputs (cameras, rays, a mesh) are made here and handed to both runs, because the
Python side's own libm calls (math.tan in frame_bounds) pick FMA variants on CPUs that
have FMA and may differ there in the last bit.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from views import DIGEST_SCRIPT

from vastray.build import build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile

QEMU = shutil.which("qemu-x86_64")
pytestmark = pytest.mark.skipif(
    platform.machine() != "x86_64" or QEMU is None,
    reason="needs an x86-64 Linux host with qemu-x86_64 (Debian's qemu-user)",
)

# CPU model -> the path the module must pick on it.
CPUS = {"Nehalem": "sse2", "SandyBridge": "avx"}
# CPU model -> OpenBLAS's name for it. numpy's OpenBLAS takes the host's kernels even
# under QEMU (on an AMD EPYC with AVX-512 it said "Core: Haswell" under -cpu Nehalem and
# SandyBridge, and an AVX instruction of its own then stopped `import numpy`), so the
# emulated run names the emulated CPU to it: the test is about this module's code.
OPENBLAS_CORES = {"Nehalem": "Nehalem", "SandyBridge": "Sandybridge"}

_SCRIPT = (
    DIGEST_SCRIPT
    + r"""
model, inputs, mesh, built = sys.argv[1:5]
data = np.load(inputs)
out = {"isa": native.isa(), "supported": native.supported_isas()}
cameras = {
    str(view): Camera(eye=tuple(map(float, e)), target=tuple(map(float, t)), width=64, height=48)
    for view, (e, t) in enumerate(zip(data["eyes"], data["targets"]))
}
with ModelFile(model) as f:
    scene = f.to_scene()
with OutOfCoreModel(model, make_cache(64 << 20)) as ooc:
    out.update(frame_digests(scene, ooc, cameras, (1, 16), 4))
    o, d = data["origins"], data["directions"]
    hits = scene.intersect(o, d)
    out["intersect"] = digest(hits["t"], hits["prim"], hits["u"], hits["v"])
    out["occluded"] = digest(scene.occluded(o, d, 0.0, float(data["ao_tmax"])))
    picked = ooc.pick(o, d, timeout=600.0)
    out["pick"] = digest(picked.t, picked.prim, picked.complete)
build_model(mesh, built)
with open(built, "rb") as f:
    out["build"] = hashlib.sha256(f.read()).hexdigest()[:16]
print(json.dumps(out))
"""
)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    work = tmp_path_factory.mktemp("isa-emulated")
    model = work / "plant.vast"
    build_model("scene:plant:30000:3", model)
    with ModelFile(model) as f:
        lo, hi = (np.asarray(v) for v in f.bounds)
    overview = frame_bounds(lo, hi, width=64, height=48)
    e, t = np.asarray(overview.eye), np.asarray(overview.target)
    close = Camera(eye=tuple(t + (e - t) * 0.3), target=overview.target, width=64, height=48)
    origins, directions = overview.primary_rays()
    np.savez(
        work / "inputs.npz",
        eyes=np.array([overview.eye, close.eye]),
        targets=np.array([overview.target, close.target]),
        origins=origins[::5],
        directions=directions[::5],
        ao_tmax=0.2 * float(np.linalg.norm(hi - lo)),
    )
    mesh = work / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=4).export(mesh)
    (work / "script.py").write_text(_SCRIPT)
    return {"work": work, "model": model, "inputs": work / "inputs.npz", "mesh": mesh}


def run_script(inputs: dict[str, Path], name: str, prefix: list[str]) -> dict[str, object]:
    env = dict(os.environ)
    env.pop("VASTRAY_ISA", None)
    if name in OPENBLAS_CORES:
        env["OPENBLAS_CORETYPE"] = OPENBLAS_CORES[name]
    built = inputs["work"] / f"{name}.vast"
    args = [str(inputs[k]) for k in ("model", "inputs", "mesh")] + [str(built)]
    result = subprocess.run(
        [*prefix, str(inputs["work"] / "script.py"), *args],
        capture_output=True, text=True, env=env, timeout=900, cwd=inputs["work"],
    )  # fmt: skip
    stderr = "\n".join(line for line in result.stderr.splitlines() if "TCG doesn't support" not in line)
    illegal = result.returncode == -4
    hint = " (an instruction this CPU lacks: AVX code outside the kernels?)" if illegal else ""
    assert result.returncode == 0, f"{name}: exit {result.returncode}{hint}\n{stderr[-3000:]}"
    return json.loads(result.stdout)


@pytest.fixture(scope="module")
def reference(inputs: dict[str, Path]) -> dict[str, object]:
    return run_script(inputs, "host", [sys.executable])


@pytest.mark.parametrize("cpu", sorted(CPUS))
def test_runs_on_older_cpus_with_the_same_answers(
    inputs: dict[str, Path], reference: dict[str, object], cpu: str
) -> None:
    # The real interpreter, told it runs as the venv's (argv[0]), so that the venv's
    # site-packages are found as they are in the reference run.
    python = os.path.realpath(sys.executable)
    emulated = run_script(inputs, cpu, [QEMU, "-cpu", cpu, "-0", sys.executable, python])
    expected = CPUS[cpu]
    assert emulated.pop("isa") == expected
    supported = emulated.pop("supported")
    assert supported[-1] == expected and "avx2" not in supported
    host = {k: v for k, v in reference.items() if k not in ("isa", "supported")}
    assert emulated.keys() == host.keys()
    differ = [k for k, v in host.items() if emulated[k] != v]
    assert not differ, f"{cpu} ({expected}) differs from this machine ({reference['isa']}) in {differ}"
