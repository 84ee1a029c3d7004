"""Many scenes on Ray Serve: ``edmcgs-serve --ray CONFIG`` (or ``serve run``), an optional extra (``ray``).

A gateway deployment (the FastAPI ingress, ``gateway.py``) lists the scenes at ``/scenes`` and forwards
``/scenes/{name}/...`` to that scene's deployment (``scene.py``), whose replicas each run the
single-process service (``edmcgs.server.app.create_app``) in-process: the same routes, errors and
websocket as ``edmcgs-serve``. ``config.py`` reads the YAML that lists the scenes; ``app.py`` builds the
Serve application from it. Only this package imports ``ray``; the default server never imports it.
"""
