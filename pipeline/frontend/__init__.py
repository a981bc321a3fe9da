"""The image front end: images and their intrinsics, SIFT features, pair selection and matching."""
