"""Software in the loop: the plant and the controller as processes over virtual CAN."""
