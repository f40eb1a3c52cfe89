"""Path guiding: a field that learns, while rendering, where light comes from
(:mod:`~mitsuba_plugins.guiding.field`), guided directions in media (resampling) and at
surfaces (a mixture with the BSDF) and the records that train the field
(:mod:`~mitsuba_plugins.guiding.sampling`), and the render
of passes that learns and guides within one ``mi.render`` call
(:mod:`~mitsuba_plugins.guiding.render`). docs/method.md section 13."""
