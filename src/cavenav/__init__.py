"""cavenav: VLM-steered navigation of an underwater vehicle through unseen caves."""

__version__ = "0.1.0"

__all__ = ["__version__"]
