"""trivla-drake: the TriVLA vision-language-action policy as Drake systems."""

__version__ = "0.1.0"
