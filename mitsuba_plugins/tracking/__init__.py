"""Light transport through media: majorants and their grid, the one walk along a ray and
the rules it applies (free flights, transmittance, marching), the trackers through which
the walk sees a medium, shadow rays, equiangular sampling, and the replay that
differentiates a path. docs/architecture.md draws the modules in dependency order."""
