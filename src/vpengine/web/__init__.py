"""The live view of a running engine: a page, a JSON API and Prometheus metrics (``pip install 'vpengine[web]'``).

::

    from vpengine import Engine
    from vpengine.web import serve

    with Engine("configs/tiny.yaml") as engine, serve(engine, port=8080) as view:
        print(view.url)  # open it in a browser; submit frames as usual

See :mod:`vpengine.web.server` for the routes and who may use them.
"""

from vpengine.web.pictures import FrameLookup, Pictures, render
from vpengine.web.server import PICTURE_PERIOD_S, STATS_PERIOD_S, WebServer, serve

__all__ = [
    "PICTURE_PERIOD_S",
    "STATS_PERIOD_S",
    "FrameLookup",
    "Pictures",
    "WebServer",
    "render",
    "serve",
]
