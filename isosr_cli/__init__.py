"""The `isosr` command line: one entry point, a subcommand per job. Nothing imports it."""
