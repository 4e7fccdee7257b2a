"""HDF5 LOD archives: one layout (``layout``), its JSON Schema (``schema``), a streaming writer
of one scan (``scanwriter``), atomic archive writes that grow in O(new data) (``writer``, with
the file-system side in ``files``), the index of part files (``index``), a reader with prefix
level queries (``reader``; the arithmetic is :mod:`lodbuilder.levels`), remote reads over HTTP/S3 (``remote``) and a validator
(``validate``).

Public entry points: :func:`lodbuilder.build_archive` and :func:`lodbuilder.open_archive`;
:class:`~lodbuilder.archive.scanwriter.ScanWriter` and
:func:`~lodbuilder.archive.writer.register_parts` for builds that write scans themselves.
Nothing heavy is imported here.
"""
