"""Scenes of the application: scene folders on disk, the seeded synthetic rooms written in that
format, procedural Gaussians made in code, and named scenes seen by one camera."""
