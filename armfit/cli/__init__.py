"""armfit's command line: a Click group with one module per subcommand."""


__all__: list[str] = []
