"""`fit` (`fit.py`, on `optimistix.least_squares`) and the multiple-shooting residuals it
minimizes (`shooting.py`)."""
