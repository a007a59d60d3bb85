"""What every command shares: its start (startup, which an entry point imports before anything
else, so this file imports nothing), its console and one-line errors (console, common), the text of
`--help` (help_text), names imported on first use (deferred) and the optional extras (extras)."""
