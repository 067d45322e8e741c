"""The command line: `polydda` (:mod:`.main`, one `cmd_*` function per subcommand) and the
small REST client it submits scenes with (:mod:`.client`)."""
