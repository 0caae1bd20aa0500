"""The HTTP surface: one module per resource (``views``, ``grasps``, ``sessions``, ``inspector``),
the request and response bodies (``schemas``), errors as 4xx (``errors``), the API document
(``openapi``), the middleware in front of every route, the route dependencies (``depends``) and
the bearer-token checks (``auth``, standard library only)."""
