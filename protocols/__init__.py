"""Sans-IO formats: values to bytes and back. Imports only the standard library and numpy."""
