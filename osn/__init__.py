"""osn: Object Scale Network (ICML 2024) in PyTorch, with sampling, best-of-N evaluation and export."""

__version__ = "0.1.0"
