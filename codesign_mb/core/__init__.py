"""The bottom layer: strict config loading, the component registry, results I/O, statistics, seeds.

Nothing here imports another layer of the package; the registry names components by import
path (``"package.module:attribute"``), so it knows every kind without importing any.
"""
