"""The sensor layer: everything between an event camera (or a recording of one) and the model input I_E."""
