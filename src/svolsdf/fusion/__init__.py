"""svolsdf.fusion"""
