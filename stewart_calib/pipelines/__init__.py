"""What a user runs: one module per ``stewart-calib`` subcommand (``add_parser``, ``main``)."""
