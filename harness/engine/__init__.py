"""The training engine every detector shares: data pipeline and augmentation (``data``, ``augment``), optimiser and
schedule (``optim``), EMA (``ema``), checkpoints (``checkpoint``), the training loop (``trainer``) and inference to
COCO results (``predict``). The orchestration of whole runs (prepare, folds, seeds, results store) is
``harness.runner``.
"""
