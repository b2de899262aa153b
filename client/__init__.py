"""vastray.client: the Python client of the render service.

    from vastray.client import Client
    vr = Client("http://127.0.0.1:8000/?key=…")       # the URL `vastray serve` prints
    job = vr.build("scene:plant:1e6:3"); vr.wait(job, progress=True)
    vr.render(job.model_id, camera={"width": 1280, "height": 720}).save("plant.png")
    with vr.view(job.model_id, viewport=(1280, 720)) as view:   # streamed frames
        view.set_camera(eye=(40, 30, 40), target=(0, 5, 0))
        view.final().image                                      # numpy (H, W, 3)

`AsyncClient` and `AsyncView` are the same API for asyncio code.
"""

from vastray.client.api import AsyncClient, BuildFailedError, VastrayError
from vastray.client.frames import Frame
from vastray.client.stream import AsyncView
from vastray.client.sync import Client, View

__all__ = ["AsyncClient", "AsyncView", "BuildFailedError", "Client", "Frame", "VastrayError", "View"]
