"""The data contract: the tables' columns and types, the rules a row must meet, and the validation
that turns bad input into ``rejects`` rows with a reason. Built on :mod:`tertiary.core` only."""
