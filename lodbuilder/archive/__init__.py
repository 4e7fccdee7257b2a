"""HDF5 LOD archives: one layout (``layout``), its JSON Schema (``schema``), an atomic writer
(``writer``), a reader with prefix level queries (``reader``, ``levels``) and a validator
(``validate``). ``demo_surface`` generates scan-like test surfaces.

Public entry points: :func:`lodbuilder.build_archive` and :func:`lodbuilder.open_archive`.
Nothing heavy is imported here.
"""
