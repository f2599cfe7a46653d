"""Tables, curves and analyses built from run directories."""
