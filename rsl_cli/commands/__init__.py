"""One module per command; each defines ``ORDER`` (position in --help) and ``register(app)``."""
