"""``python -m service [--host H] [--port P]``: uvicorn with the shipped default model.

Every other setting comes from ``GRASP_*`` environment variables (see :class:`Settings`).
"""

from __future__ import annotations

import argparse
import ipaddress
import sys

from pydantic import ValidationError

from completion.cli import DefaultsAndRawDescription
from service.settings import Settings


def main(argv: list[str] | None = None) -> None:
    defaults = Settings()
    width = max(map(len, Settings.model_fields)) + 2
    parser = argparse.ArgumentParser(
        prog="python -m service",
        description="Serve the grasp-planning HTTP API with uvicorn (OpenAPI docs at /docs).",
        epilog="settings (environment variables):\n"
        + "\n".join(
            f"  GRASP_{name.upper():<{width}}{field.description} (default {field.default})"
            for name, field in Settings.model_fields.items()
        ),
        formatter_class=DefaultsAndRawDescription,
    )
    parser.add_argument("--host", default=defaults.host, help=f"default {defaults.host}")
    parser.add_argument("--port", type=int, default=defaults.port, help=f"default {defaults.port}")
    args = parser.parse_args(argv)
    try:
        settings = Settings(host=args.host, port=args.port)
    except ValidationError as exc:
        parser.error(str(exc))
    if settings.token is None and not _is_loopback(settings.host):
        print(
            f"warning: serving on {settings.host} without a token; set GRASP_TOKEN to require "
            "'Authorization: Bearer <token>'",
            file=sys.stderr,
        )
    import uvicorn

    from service.server.connections import check_uvicorn, serve

    check_uvicorn(uvicorn.__version__)  # before the model loads
    from service.app import create_app

    serve(create_app(settings), settings)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


if __name__ == "__main__":
    main()
