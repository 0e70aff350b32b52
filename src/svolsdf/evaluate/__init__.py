"""svolsdf.evaluate"""
