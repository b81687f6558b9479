"""The `gmmap` subcommands, a module each: the flags it takes (`add_<command>`, shared flags in
services/cli_flags.py) and what it runs (`cmd_<command>`); services/cli.py puts them together."""
