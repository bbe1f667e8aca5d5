"""One module per `vrscroll` command."""
