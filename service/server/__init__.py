"""``python -m service`` as a process: the connection-level guards in front of uvicorn
(``connections``)."""
