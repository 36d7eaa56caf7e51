"""What is made from a finished run on demand: meshes and point clouds, the live viewer."""
