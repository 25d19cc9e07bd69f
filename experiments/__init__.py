"""Experiments reproducing the papers' tables and figures (scripts on top of the library).

The experiments compute in float64 where their inputs are float64, as their stored results were made: this
package, a program rather than a library, enables ``jax_enable_x64`` for the process that imports it.
"""

import jax

jax.config.update("jax_enable_x64", True)
