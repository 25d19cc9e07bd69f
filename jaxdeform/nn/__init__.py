"""Network pieces shared by the methods: mesh convolution, autoencoder block, losses."""
