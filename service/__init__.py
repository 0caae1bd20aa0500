"""HTTP service: stream depth views of an object into a session, get a BarrettHand grasp.

``python -m service [--host H] [--port P]`` serves the shipped MVP on 127.0.0.1:8000 with the
sessions in ``./grasp_store.sqlite``; every setting is a ``GRASP_*`` environment variable
(:class:`service.settings.Settings`). OpenAPI docs at ``/docs``. A session, from Python::

    import httpx
    from completion.scenes import make_sequence
    from service.load import scene_views

    views = scene_views(make_sequence("camera_pan", "test", 0, keep_depth=True))
    sid = httpx.post("http://127.0.0.1:8000/views", json=views[0]).json()["session_id"]
    for body in views[1:]:
        httpx.post("http://127.0.0.1:8000/views", json=body | {"session_id": sid})
    grasp = httpx.get("http://127.0.0.1:8000/grasp", params={"session_id": sid}, timeout=60)

Stages, lowest first (docs/design.md §2): ``intake`` (bodies parsed off the event loop, their byte
budgets, views decoded and their frames checked) · ``settings`` · ``store`` (the interface, SQLite,
Redis, locks) · ``engine`` (stream step, completion, mesh; planner workers) · ``services`` (what the
lifespan builds) · ``api`` (one module per resource, schemas, errors, the API document, middleware,
token checks) · ``app`` (factory, lifespan) · ``server`` (connection guards) · ``load`` (load
generator, and ``scene_views``: simulated scenes as request bodies). The Python client a robot
program uses, and the wire types the service shares with it, are the ``grasp_client`` package
(``clients/python/``).
"""
