"""The ``ctid`` command: one module per subcommand, text reports and figures."""

__all__: list = []
