"""A test assembly: three boxes in a row along x, each an OBJ object (a part)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np

# (name, lower corner, side)
BOXES = [
    ("pump housing", (0.0, 0.0, 0.0), 1.0),
    ("pump impeller", (2.0, 0.0, 0.0), 1.0),
    ("Valve", (4.0, 0.0, 0.0), 1.0),
]
CELLS = 6  # each box face is CELLS x CELLS quads


def box_obj(lo: tuple[float, float, float], side: float, first_vertex: int) -> tuple[list[str], int]:
    """A closed box of 6 * CELLS^2 * 2 triangles as OBJ lines, wound counter-clockwise
    seen from outside (a solid, so a section plane through it shows a cap)."""
    lines, faces = [], []
    n = first_vertex
    grid = np.linspace(0.0, side, CELLS + 1)
    for axis in range(3):
        for high in (0.0, side):
            u, v = [a for a in range(3) if a != axis]
            # The triangles below turn from +v towards +u: their normal is (e_v x e_u),
            # which is -1 or +1 times e_axis; outward is + on the high face.
            if np.cross(np.eye(3)[v], np.eye(3)[u])[axis] * (1 if high else -1) < 0:
                u, v = v, u
            base = n
            for i in grid:
                for j in grid:
                    p = np.array(lo, dtype=np.float64)
                    p[axis] += high
                    p[u] += i
                    p[v] += j
                    lines.append(f"v {float(p[0])!r} {float(p[1])!r} {float(p[2])!r}")
                    n += 1
            for i in range(CELLS):
                for j in range(CELLS):
                    a = base + i * (CELLS + 1) + j
                    faces.append(f"f {a} {a + 1} {a + CELLS + 2}")
                    faces.append(f"f {a} {a + CELLS + 2} {a + CELLS + 1}")
    return lines + faces, n


def write_assembly(path: Path) -> Path:
    lines, n = ["# three parts"], 1
    for name, lo, side in BOXES:
        body, n = box_obj(lo, side, n)
        lines += [f"o {name}", *body]
    path.write_text("\n".join(lines) + "\n")
    return path


def build_assembly(api: httpx.Client, folder: Path) -> dict[str, Any]:
    """Uploads the assembly to a server, builds it and returns the model's info."""
    from serverproc import wait_for_job

    path = write_assembly(folder / "assembly.obj")
    up = api.post(
        "/api/uploads", params={"filename": "assembly.obj", "register": "true", "name": "assembly"},
        content=path.read_bytes(),
    )  # fmt: skip
    assert up.status_code == 201, up.text
    job = wait_for_job(api, up.json()["created"]["job"]["id"])
    assert job["state"] == "succeeded", job
    return dict(api.get(f"/api/models/{job['model_id']}").json())
