"""Example dataset plugin for rgbt-harness (see README.md): the ``example-folders`` dataset."""

__version__ = "0.1.0"
