"""Layer 5: using a trained run: rendering views, scoring them against the ground truth, the error
images, its mesh and that mesh measured against the scene's true surface, and the HTML report."""
