"""One thin module per CLI command: parse flags, load the config, call the library."""
