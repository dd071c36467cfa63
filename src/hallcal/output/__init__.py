"""What a person or a firmware project reads: figures, the HTML report and the C export."""
