"""Attention controllers: capture of attention maps and zero-shot editing by modulating them."""
