"""What the drivers truly share: serial link, pty helper, parameters, diagnostics, run_node."""
