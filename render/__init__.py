"""pmjax.render: pyrender display of refinement results (see docs/)."""
