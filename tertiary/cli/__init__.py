"""The command line: thin commands over the library's functions (one module per command group)."""
