"""The batch job: its configuration, the declared stages in order, the streaming run over windows,
the whole-run stages at the end and the run record."""
