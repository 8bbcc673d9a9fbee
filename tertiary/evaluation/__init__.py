"""Evaluation of any air picture against a reference: matching to truth, accuracy, consistency and
surveillance metrics, indicators, radar evaluation, the posterior Cramér–Rao bound, and the
requirements judged from the metrics."""
