"""One module per `procam` sub-command (see app/cli.py for the contract)."""
