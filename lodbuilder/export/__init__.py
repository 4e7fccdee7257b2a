"""Levels written for other tools: a COPC file (``export/copc.py``: QGIS, Potree, viewer.copc.io,
CloudCompare) and a standalone web page (``export/web.py``). The flow is archive -> level ->
export: each exporter takes an archive scan and a level size; nothing heavy is imported here."""
