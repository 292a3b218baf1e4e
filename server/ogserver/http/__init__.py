"""The server's HTTP listeners (the web view, /metrics) on aiohttp, held to one policy (``policy.py``)."""
