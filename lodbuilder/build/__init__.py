"""The build pipeline, below the public API: inputs -> scan jobs (in memory or tiled) -> executor
(this process, a process pool or Dask) -> part archives -> the archive.

``runner`` plans and runs a build, ``jobs`` is what a worker runs for one scan, ``record`` orders an
in-memory scan into the record the archive writer stores, ``tiled/`` is the out-of-core path,
``executors`` are where jobs run, ``inputs`` expands files, directories, globs and manifests, and
``options`` holds the one :class:`~lodbuilder.build.options.BuildOptions` every build path takes.
Nothing heavy is imported here.
"""
