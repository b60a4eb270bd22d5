"""One module per ``wara`` verb; each exposes ``register(subparsers)``."""
