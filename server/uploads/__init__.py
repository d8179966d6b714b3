"""Motion files uploaded into a draft study's assets, and the job that builds and renders their clips."""
