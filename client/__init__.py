"""vastray.client: the Python client of the render service (REST and streaming)."""
