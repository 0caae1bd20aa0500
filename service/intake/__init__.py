"""What enters with ``POST /views``: the body parsed and decoded off the event loop (``parsing``),
its memory budget (``memory``), the decoding into a :class:`completion.stream.View` (``inputs``),
the frame checks against what the camera saw (``frames``), and the worker processes' start
(``workers``). Every rule about a view is checked here, once."""
