"""armfit's command line: a Click group with one module per subcommand."""
