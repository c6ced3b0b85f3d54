"""What the commands do: evaluation, reports, reproduction, analysis of a pair, figures."""
