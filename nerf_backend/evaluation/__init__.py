"""Layer 5: using a trained run: rendering views, scoring them against the ground truth, the error
images and the HTML report."""
