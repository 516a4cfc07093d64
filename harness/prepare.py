"""Old home of dataset preparation, kept so existing imports (``from harness.prepare import prepare``) work: the
prepared cache is the ``harness.cache`` package, whose public names this module re-exports."""

from harness.cache import (PREPARE_VERSION, FoldSupport, PreparedDataset, PreparedWriter, cache_form, cache_key,
                           cache_root, coco_path, fold_indices, fold_support, open_source, plugin_code_fingerprint,
                           prepare, resolve_folds, select_folds)

__all__ = ["PREPARE_VERSION", "FoldSupport", "PreparedDataset", "PreparedWriter", "cache_form", "cache_key",
           "cache_root", "coco_path", "fold_indices", "fold_support", "open_source", "plugin_code_fingerprint",
           "prepare", "resolve_folds", "select_folds"]
