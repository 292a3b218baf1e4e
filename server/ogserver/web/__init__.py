"""The web view: each session's map as 3D Gaussians in the browser (three.js and Spark), over HTTP."""
