"""quietframe.experiments: ablations and one-off measurements (README.md: question, result,
whether current or superseded). Nothing in the product imports them."""
