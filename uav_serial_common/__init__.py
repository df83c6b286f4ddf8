"""What the drivers truly share: the serial link, the pty helper, parameters, diagnostics, run_node."""
