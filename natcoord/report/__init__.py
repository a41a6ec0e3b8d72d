"""HTML report of a results directory: ``write_report(results_dir, references)``."""

from .html import write_report

__all__ = ["write_report"]
