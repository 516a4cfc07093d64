"""The prepared-sample cache: every dataset's aligned samples, prepared once and read by every run.

* ``key``: where a prepared dataset lives (cache root, form folder) and its key (fingerprint, sensing, plugin code);
* ``forms``: the two forms (``compact``, ``raw``), their lossless codecs and references to source files;
* ``writer``: ``PreparedWriter``, samples validated and written into a temporary folder renamed into place;
* ``reader``: ``PreparedDataset``, samples, encoded channels, COCO ground truth and support, in every form alike;
* ``preparation``: ``prepare(dataset, cfg)``, open the plugin, check what it returns, write or reuse, guard inputs;
  ``cached(dataset, key)``, what the cache holds under a run's key, without preparing;
* ``folds``: the folds of a prepared dataset and the COCO files of their splits;
* ``admin``: housekeeping (``harness cache``): listing, sizes, last use, removing what is unused.

The names below are the package's public surface (``harness.prepare`` re-exports them for older imports).
"""

from harness.cache.folds import FoldSupport, coco_path, fold_indices, fold_support, resolve_folds, select_folds
from harness.cache.key import PREPARE_VERSION, cache_form, cache_key, cache_root, plugin_code_fingerprint
from harness.cache.preparation import cached, open_source, prepare
from harness.cache.reader import PreparedDataset
from harness.cache.writer import PreparedWriter

__all__ = [
    "PREPARE_VERSION",
    "FoldSupport",
    "PreparedDataset",
    "PreparedWriter",
    "cache_form",
    "cache_key",
    "cache_root",
    "cached",
    "coco_path",
    "fold_indices",
    "fold_support",
    "open_source",
    "plugin_code_fingerprint",
    "prepare",
    "resolve_folds",
    "select_folds",
]
