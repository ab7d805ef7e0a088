"""A headless QGIS application that records its warnings, for the PyQGIS check scripts
(run by Debian's /usr/bin/python3; imports nothing of standgrid)."""

from __future__ import annotations

from typing import Any


def start_qgis() -> tuple[Any, list[str]]:
    """``(app, messages)``: an initialised QgsApplication and the list its message log's
    warnings (and worse) are appended to, as ``"tag: message"``."""
    from qgis.core import Qgis, QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    messages: list[str] = []

    def log(message: str, tag: str, level: int) -> None:
        if level >= Qgis.Warning:
            messages.append(f"{tag}: {message}")

    QgsApplication.messageLog().messageReceived.connect(log)
    app._standgrid_log = log  # the slot lives as long as the application
    return app, messages
