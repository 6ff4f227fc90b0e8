"""omnidl.synth"""
