"""The gpi_tool subcommands: each takes parsed arguments, writes its files, returns a JSON-able dict."""
